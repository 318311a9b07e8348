"""The command line as a careful user meets it: one-line errors naming the file, exit status 2,
no tracebacks, strict JSON (issue 16, first part)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from neuromotor.cli import main, metrics_json


def test_version(capsys):
    from neuromotor import __version__

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.strip() == f"neuromotor {__version__}"


@pytest.mark.parametrize("command", [["inspect"], ["idyn", "-o", "never.npz"], ["export-mjcf", "-o", "never.xml"]])
def test_a_directory_as_the_clip_is_a_one_line_error(command, tmp_path, capsys):
    argv = [command[0], str(tmp_path)] + command[1:]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(tmp_path) in err and "Is a directory" in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("flags", [[], ["--json"]])  # a short table (flushed at exit) and a long one
def test_output_closed_early_is_not_an_error(flags):
    """`neuromotor inspect | head`: the reader goes away before the table is written."""
    proc = subprocess.Popen([sys.executable, "-m", "neuromotor.cli", "inspect", *flags],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 0 and "Traceback" not in err and "BrokenPipe" not in err


def test_metrics_json_is_strict_and_says_why_a_value_is_null():
    out = metrics_json({"peak_deviation_deg": 1.5, "recovery_time_s": math.nan, "diverged": False})
    text = json.dumps(out, allow_nan=False)  # raises on NaN
    back = json.loads(text)
    assert back["recovery_time_s"] is None and back["peak_deviation_deg"] == 1.5
    assert "recovery_threshold_deg" in back["null_reasons"]["recovery_time_s"]
    assert "null_reasons" not in metrics_json({"peak_deviation_deg": 1.5})


def test_every_option_says_what_it_means():
    """Every positional and option of every command has a help text (meaning and units)."""
    import argparse

    from neuromotor.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    missing = [f"{name} {'/'.join(a.option_strings) or a.dest}"
               for name, sp in sub.choices.items() for a in sp._actions
               if not isinstance(a, argparse._HelpAction) and not (a.help and a.help.strip())]
    assert not missing, missing


def test_every_command_that_reads_a_clip_takes_the_clip_options():
    from neuromotor.cli import build_parser

    parser = build_parser()
    clip_opts = ["--units", "cm", "--up-axis", "1", "--stature", "1.7", "--body-mass", "70", "--sex", "male",
                 "--simulate-extremities"]
    for argv in (["inspect"], ["idyn", "-o", "x.npz"], ["simulate", "-o", "x.npz"], ["export-mjcf", "-o", "x.xml"],
                 ["bench"]):
        args = parser.parse_args(argv + clip_opts)
        assert (args.units, args.up_axis, args.stature, args.body_mass, args.sex) == ("cm", 1, 1.7, 70.0, "male")
        assert args.simulate_extremities


def test_bench_runs_on_any_rig_with_the_clip_options():
    """`neuromotor bench CLIP` once needed a body called Chest2: the default hit now names the
    chest keyword, and the clip options reach the model."""
    from conftest import ALL_CLIPS
    from neuromotor.studies import bench

    setup = bench._setup(ALL_CLIPS["bandai_kick_22joint_6ch"], 0.05, "nullspace", {"units": "cm", "up_axis": 1})
    model = setup.model
    assert model.body_names[int(setup.pulses.body[0])] == "Chest" and model.n_bodies == 19
    assert setup.character.anatomy.units == "cm" and float(model.gravity[1]) == -9.81


@pytest.mark.parametrize(
    "sim, needle",
    [
        ("still = 99.0", "field 'sim.still' = 99 s is outside the clip (0 to 15.133 s)"),
        ("still = -1.0", "field 'sim.still' must be >= 0, got -1.0"),
        ('still = "noon"', "field 'sim.still' must be a finite number, got 'noon'"),
        ('driven_joints = ["trunk", "tail"]', "field 'sim.driven_joints[1]' = 'tail' matches no body; bodies are "),
        ('driven_joints = ["arms"]', "field 'sim.driven_joints[0]' = 'arms' matches no body on this rig"),
    ],
)
def test_bad_still_and_driven_joints_are_one_line_errors(sim, needle, tmp_path, capsys):
    """[sim] still outside the clip, negative or not a number, and a driven_joints entry that
    matches nothing (a name, or a group this rig lacks: a chain has no arms): exit 2, one line
    naming the file and the field, no run file."""
    from synthetic_rigs import chain_text

    clip = ""
    if "arms" in sim:
        (tmp_path / "chain.bvh").write_text(chain_text())
        clip = 'clip = "chain.bvh"\n'
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(f"{clip}[sim]\nduration = 0.5\n{sim}\n")
    out = tmp_path / "run.npz"
    assert main(["simulate", str(cfg), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(cfg) in err and needle in err, err
    assert "Traceback" not in err and not out.exists()


@pytest.mark.parametrize("frames", [1, 3])
def test_a_clip_too_short_for_the_spline_is_a_one_line_error(frames, tmp_path, capsys):
    """A single pose or a stub of 2-3 frames (the capture is a cubic spline through at least 4):
    every command that builds the capture stops with exit 2 and one line naming the file and
    the count, and writes nothing. Four frames load."""
    from conftest import CLIPS

    text = CLIPS["mocapbank"].read_text()
    head, motion = text.split("MOTION", 1)
    lines = [ln for ln in motion.strip().splitlines() if ln.strip()]

    def clip(n):
        path = tmp_path / f"stub{n}.bvh"
        path.write_text(head + f"MOTION\nFrames: {n}\n{lines[1]}\n" + "\n".join(lines[2 : 2 + n]) + "\n")
        return path

    short, out = clip(frames), tmp_path / "run.npz"
    for argv in (["inspect", str(short)], ["simulate", "--clip", str(short), "-o", str(out)]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and str(short) in err and f"{frames} frame(s)" in err, err
        assert "at least 4" in err and "Traceback" not in err and not out.exists()
    assert main(["inspect", str(clip(4))]) == 0


def test_a_push_point_far_outside_its_body_is_warned_about():
    """A pulse's point is metres in the body's frame: one written in cm (10 for 10 cm) is a 10 m
    lever that turns the body hard with no error. It is warned about, naming the field, the body
    and the distance; the shipped configs' points (up to 0.15 m on the trunk) and a point near a
    small body (a hand) are not."""
    from neuromotor.config import simulation_config
    from neuromotor.model.load import load_character
    from neuromotor.studies.simulate import body_lookup, point_warnings

    character, _ = load_character()
    index = body_lookup(character.model, "c.toml", character)

    def warned(body, point):
        push = {"kind": "force", "body": body, "point": point, "direction": [0.0, 0.0, 1.0], "magnitude": 10.0,
                "start": 0.5, "duration": 0.1}
        cfg = simulation_config({"perturbation": [push]}, "c.toml")
        return point_warnings(cfg.perturbations, character, index, "c.toml")

    (line,) = warned("chest", [0.0, 10.0, 0.0])
    assert line.startswith("c.toml: perturbation[0].point is 10 m from Chest2's joint") and "reach" in line
    assert warned("chest", [0.0, 0.15, 0.0]) == () and warned("chest", [0.0, 0.1, 0.0]) == ()
    assert warned("LeftWrist", [0.0, -0.08, 0.0]) == ()  # on the hand
    assert len(warned("LeftWrist", [0.0, -0.8, 0.0])) == 1  # a forearm's length beyond it
