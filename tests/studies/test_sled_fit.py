"""Issue 37 end to end: a sled test. A still upright pose of a shipped clip, trunk and pelvis
belted, each subject's own recorded base acceleration (CSV, g and ms), head pitch and the head's
displacement relative to the chest as corridors; (ks, kd) and the reflex delay fitted from 3x off
come back to the truth, and the same cases through simulate give the fit's curves.

The full study (h = 1 ms, 4 subjects, noise, coverage over seeds) is experiments/sled_fit.py;
this is its cheap twin: 2 subjects, 0.3 s at h = 1/120 s, noise-free corridors.
"""

import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.config.parse import simulation_config
from neuromotor.studies import fit as F
from neuromotor.studies.simulate import load_character, prepare, run
from neuromotor.studies.targets import write_series_csv

H, ONSET = 1.0 / 120.0, 0.025
TRUTH = {"ks": 1500.0, "kd": 60.0, "reflex_delay": 0.03}
START = {"ks": 4500.0, "kd": 20.0, "reflex_delay": 0.09}


@pytest.fixture(scope="module")
def bank():
    return load_character(CLIPS["mocapbank"])


def still_time(character) -> float:
    return character[0].anatomy.reference_frame * character[0].clip.frame_time


def write_inputs(folder, n=2):
    for i in range(n):
        peak, dur = 15.0 * (0.9 + 0.2 * i), 100.0 * (1.1 - 0.2 * i)
        t = np.arange(-10.0, dur + 10.5, 1.0)
        a = np.where((t >= 0) & (t <= dur), peak * np.sin(np.pi * np.clip(t / dur, 0, 1)), 0.0)
        (folder / f"acc{i}.csv").write_text("time,t1\n" + "\n".join(f"{x:g},{float(y)!r}" for x, y in zip(t, a)) + "\n")


def config(folder, still, gains, n=2, fit=True):
    data = {
        "clip": str(CLIPS["mocapbank"]),
        "sim": {"still": still, "start": 0.0, "duration": 0.3, "h": H, "driven_joints": ["trunk", "pelvis"]},
        "gains": {"ks": gains["ks"], "kd": gains["kd"]},
        "reflex": {"gain": 600.0, "delay": gains["reflex_delay"]},
        "perturbation": [{"kind": "base", "direction": "backward", "file": str(folder / f"acc{i}.csv"), "unit": "g",
                          "time_unit": "ms", "start": ONSET} for i in range(n)],
    }
    if fit:
        data["fit"] = {"parameters": ["ks", "kd", "reflex_delay"], "max_steps": 60, "leave_one_out": False,
                       "target": [
                           {"kind": "body_angle", "body": "head", "axis": "left", "time_unit": "ms",
                            "angle_unit": "deg", "files": [str(folder / f"pitch{i}.csv") for i in range(n)]},
                           {"kind": "body_position", "body": "head", "relative_to": "chest", "axis": "forward",
                            "time_unit": "ms", "length_unit": "mm",
                            "files": [str(folder / f"disp{i}.csv") for i in range(n)]}]}
    return data


def write_targets(folder, times, curves):
    for i in range(curves.shape[0]):
        write_series_csv(folder / f"pitch{i}.csv", times - ONSET, np.rad2deg(curves[i, :, 0]), 2.0, "pitch", "ms")
        write_series_csv(folder / f"disp{i}.csv", times - ONSET, 1000 * curves[i, :, 1], 3.0, "head_x", "ms")


def test_sled_corridors_fit_back_the_gains_and_delay(bank, tmp_path):
    still = still_time(bank)
    write_inputs(tmp_path)
    grid = H * np.arange(37)
    write_targets(tmp_path, grid[grid >= ONSET - 1e-9], np.zeros((2, int(np.sum(grid >= ONSET - 1e-9)), 2)))
    cal = F.calibration_from_dict(config(tmp_path, still, TRUTH), "sled.toml", tmp_path, character=bank[0],
                                  traj=bank[1])
    ev = F.ResponseEvaluator(cal.problem)
    truth = ev(cal.x0)
    curves = np.asarray(truth.curves)
    assert np.all(truth.diverged == -1)
    pitch = np.rad2deg(curves[..., 0]).max(axis=1)
    assert np.all(pitch > 10.0) and pitch[1] != pitch[0]  # the heads pitch forward, each subject its own
    # The fit's forward model is simulate's: subject 0 alone through prepare + run.
    single = prepare(simulation_config(config(tmp_path, still, TRUTH, n=1, fit=False), "s.toml"), *bank)
    moved = run(single).perturbed.states
    b_head = single.model.body_names.index("Head")
    q = np.asarray(moved.quat[:, b_head])
    k0 = int(np.floor(ONSET / H + 1e-9))
    from neuromotor.studies.fit.observables import body_angle, identity_quats
    from neuromotor.model.facing import character_axes

    left = character_axes(bank[0], still)["left"]
    angle = np.asarray(body_angle(q, identity_quats(q.shape[0]), k0, left))
    i0 = int(np.argmin(abs(grid - cal.time[0])))
    np.testing.assert_allclose(angle[i0 : i0 + cal.time.size], curves[0, :, 0], rtol=0, atol=1e-10)

    write_targets(tmp_path, cal.time, curves)
    here = F.calibration_from_dict(config(tmp_path, still, START), "sled.toml", tmp_path, character=bank[0],
                                   traj=bank[1])
    res, doc = F.calibrate(here, tmp_path / "out", progress=False, evaluator=ev.with_problem(here.problem))
    assert res.status == "converged"
    for k, v in TRUTH.items():
        assert abs(res.values[k] / v - 1) < 1e-4, (k, res.values[k])
    assert abs(res.values["reflex_delay"] - TRUTH["reflex_delay"]) < 2e-3 * 0.01
