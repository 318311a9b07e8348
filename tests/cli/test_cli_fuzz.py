"""Property-based: random configs, random argument lists and random bytes thrown at every
command. Each call either succeeds (exit 0, a readable output) or fails cleanly (exit 2, one
line on stderr, no output); never a traceback, never a changed input file."""

from __future__ import annotations

import contextlib
import io
import pathlib
import shutil

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import ALL_CLIPS
from neuromotor.cli import main

COMMANDS = ["inspect", "idyn", "simulate", "render", "plot", "export-bvh", "export-mjcf", "fit", "sweep", "info"]
SETTINGS = settings(max_examples=25, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

toml_value = st.one_of(st.integers(-10**6, 10**6), st.floats(allow_nan=True), st.booleans(),
                       st.text(max_size=8), st.lists(st.floats(-10, 10), max_size=4))
toml_key = st.sampled_from(["clip", "units", "up_axis", "stature", "body_mass", "sex", "h", "start",
                            "duration", "ks", "kd", "body", "magnitude", "direction", "point", "kind", "bogus"])


def _toml_line(key, value) -> str:
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, float):
        text = "nan" if value != value else ("inf" if value == float("inf") else "-inf" if value == float("-inf")
                                             else repr(value))
    elif isinstance(value, str):
        text = '"' + value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    elif isinstance(value, list):
        text = "[" + ", ".join(_toml_line("x", v).split(" = ", 1)[1] for v in value) + "]"
    else:
        text = str(value)
    return f"{key} = {text}"


@st.composite
def configs(draw) -> str:
    top = draw(st.lists(st.tuples(st.sampled_from(["units", "up_axis", "stature", "body_mass", "sex", "bogus"]),
                                  toml_value), max_size=3))
    sim = draw(st.lists(st.tuples(st.sampled_from(["h", "start", "duration", "bogus"]), toml_value), max_size=3))
    pert = draw(st.lists(st.tuples(st.sampled_from(["body", "magnitude", "start", "direction", "kind", "point"]),
                                   toml_value), max_size=4))
    lines = [_toml_line(k, v) for k, v in top]
    lines += ["[sim]"] + [_toml_line(k, v) for k, v in sim] + ["duration = 0.05"] * (not any(k == "duration" for k, _ in sim))
    if pert:
        lines += ["[[perturbation]]"] + [_toml_line(k, v) for k, v in dict(pert).items()]
    return "\n".join(lines) + "\n"


def _snapshot(folder: pathlib.Path) -> dict:
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.is_file()}


def _call(argv, folder: pathlib.Path, output: pathlib.Path | None):
    before = _snapshot(folder)
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = main(argv)
        except SystemExit as e:  # argparse
            status = e.code
    after = _snapshot(folder)
    for name, data in before.items():
        assert after.get(name) == data, f"input {name} changed by {argv}"
    text = err.getvalue().strip()
    assert "Traceback" not in text, text
    assert status in (0, 2), (argv, status, text)
    if status == 2:
        lines = [ln for ln in text.splitlines() if ln.strip()]
        assert lines and lines[-1].startswith("neuromotor") and "error" in lines[-1], text
        if output is not None:
            assert not output.exists(), f"{argv} failed but left {output}"
    leftovers = [p.name for p in folder.iterdir() if p.name.startswith(".") and p.name not in before]
    assert not leftovers, f"temporaries left: {leftovers}"
    return status


@pytest.fixture()
def folder(tmp_path):
    shutil.copy(ALL_CLIPS["mocapbank_19joint"], tmp_path / "clip.bvh")
    (tmp_path / "noise.bin").write_bytes(bytes(range(256)) * 3)
    return tmp_path


@SETTINGS
@given(text=configs())
def test_random_configs_to_simulate(folder, text):
    cfg = folder / "c.toml"
    cfg.write_text(text)
    out = folder / "run.npz"
    if out.exists():
        out.unlink()
    status = _call(["simulate", str(cfg), "--clip", str(folder / "clip.bvh"), "-o", str(out)], folder, out)
    if status == 0:
        assert "theta" in np.load(out)


@SETTINGS
@given(command=st.sampled_from(COMMANDS), data=st.binary(max_size=300))
def test_random_bytes_as_every_input(folder, command, data):
    bad = folder / ("in.bvh" if command in ("inspect", "idyn", "export-mjcf") else
                    "in.toml" if command in ("simulate", "fit", "sweep") else "in.npz")
    bad.write_bytes(data)
    out = folder / "out_file"
    argv = [command, str(bad)]
    if command not in ("inspect", "info"):
        argv += ["-o", str(out)]
    _call(argv, folder, out)


flag = st.sampled_from(["--units", "--up-axis", "--stature", "--body-mass", "--sex", "--ks", "--kd", "--json",
                        "-o", "--frames", "--timestep", "--quiet", "--bogus"])
arg = st.one_of(st.sampled_from(["nan", "-1", "0", "1e9", "cm", "auto", "2", "", "x"]), st.text(max_size=5))


# Commands whose random argument lists cannot start a long computation (no valid config, run
# file or clip among the arguments); simulate, idyn and export-mjcf get random configs and bytes.
QUICK = ["inspect", "render", "plot", "export-bvh", "fit", "sweep", "info"]


@SETTINGS
@given(command=st.sampled_from(QUICK), extra=st.lists(st.one_of(flag, arg), max_size=5))
def test_random_argument_lists(folder, command, extra):
    out = folder / "o.out"
    _call([command, *extra], folder, out if "-o" in extra else None)
