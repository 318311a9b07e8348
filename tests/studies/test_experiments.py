"""``neuromotor experiment CONFIG``: the arm experiment end to end on the embedded clip."""

import json
import pathlib

from neuromotor.cli import main

CONFIG = pathlib.Path(__file__).resolve().parents[2] / "configs" / "exp_arm.toml"


def test_arm_experiment_from_the_command_line(tmp_path):
    text = CONFIG.read_text()
    text = text.replace("duration = 2.0", "duration = 1.2").replace('output = "../out/exp_arm"', 'output = "out"')
    text = text.replace("frames = 6", "frames = 2").replace('video = "video.gif"', 'video = ""')
    cfg = tmp_path / "arm.toml"
    cfg.write_text(text)
    assert main(["experiment", str(cfg), "--quiet"]) == 0
    numbers = json.loads((tmp_path / "out" / "metrics.json").read_text())
    # The push moves the simulated arm; every other joint is driven along the mocap and stays on it.
    assert numbers["arm"]["peak_deviation_deg"] > 1.0
    assert numbers["rest_of_body_max_deviation_deg"] < 1e-6
    assert max(numbers["per_joint_peak_deg"].values()) >= numbers["arm"]["peak_deviation_deg"]
    assert (tmp_path / "out" / "arm.png").stat().st_size > 10_000
