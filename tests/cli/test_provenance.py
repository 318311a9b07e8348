"""A Blender-style rig (dotted joint names) through inspect, simulate, export-bvh and info;
RUN.npz provenance; exported angles continuous and equal to RUN.npz theta (issue 16)."""

import hashlib
import json
import re

import numpy as np
import pytest

from neuromotor import cli
from neuromotor.config import SimulationConfig
from neuromotor.io.export import export_bvh, reread_angles
from neuromotor.studies.record import run_arrays
from neuromotor.studies.simulate import prepare, run, save_npz_atomic

from synthetic_rigs import make_rig


def _dotted(rig) -> tuple[str, dict]:
    """The rig's BVH with Blender's names: ``spine.001``, ``thigh.L``, ``hand.R``, ..."""
    new, count = {}, {}
    for name, seg, side in zip(rig.names, rig.segment, rig.side):
        if side:
            new[name] = f"{seg}.{side[0].upper()}"
        else:
            base = "spine" if seg == "trunk" else seg
            count[base] = count.get(base, 0) + 1
            new[name] = f"{base}.{count[base]:03d}"
    assert len(set(new.values())) == len(new)
    text = re.sub(r"^(\s*(?:ROOT|JOINT) )(\S+)$", lambda m: m.group(1) + new.get(m.group(2), m.group(2)),
                  rig.text, flags=re.M)
    return text, new


@pytest.fixture(scope="module")
def dotted(tmp_path_factory):
    rig = make_rig(3, fingers=False, toes=False, face=False, props=0, virtual_root=False, unit="m",
                   frames=40, twist=False, hip_link=False, six_channels=False)
    text, names = _dotted(rig)
    d = tmp_path_factory.mktemp("dotted")
    clip = d / "blender_rig.bvh"
    clip.write_text(text, encoding="utf-8")
    hit = {"kind": "force", "body": "chest", "direction": [0.0, 0.0, 1.0], "magnitude": 150.0,
           "start": 0.1, "duration": 0.1, "shape": "half_sine"}
    cfg = SimulationConfig(clip=str(clip), duration=0.3, perturbations=[hit], source="test")
    setup = prepare(cfg)
    result = run(setup)
    arrays = run_arrays(setup, result)
    npz = save_npz_atomic(d / "run.npz", arrays)
    return {"dir": d, "clip": clip, "names": names, "setup": setup, "arrays": arrays, "npz": npz}


def test_inspect_json_dofs_of_dotted_joints(dotted, capsys):
    assert cli.main(["inspect", str(dotted["clip"]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    dof_names = list(dotted["setup"].model.dof_names)
    assert any(n.count(".") == 2 for n in dof_names)  # e.g. spine.001.Xrotation
    listed = []
    for j in info["joints"]:
        assert j["name"] in dotted["names"].values()
        for dof in j["dofs"]:
            joint, channel = dof.rsplit(".", 1)
            assert joint == j["name"] and channel in ("Xrotation", "Yrotation", "Zrotation")
        listed += j["dofs"]
    assert sorted(listed) == sorted(dof_names)
    assert all(len(j["dofs"]) == 3 for j in info["joints"] if j["parent"] is not None and j["body"])


def test_simulate_and_export_round_trip_dotted(dotted):
    arrays = dotted["arrays"]
    assert all(str(n).rsplit(".", 1)[0] in dotted["names"].values() for n in arrays["dof_names"])
    assert np.isfinite(arrays["theta"]).all()
    out = export_bvh(dotted["npz"], dotted["dir"] / "out.bvh")
    back = reread_angles(out, float(str(arrays["source_units"])), arrays["dof_names"])
    assert back.shape == arrays["theta"].shape
    np.testing.assert_allclose(back, arrays["theta"], atol=1e-7)  # 0, not 2 pi


def test_export_is_continuous_when_run_theta_jumps(dotted):
    """An older RUN.npz whose theta jumps by 2 pi mid-run: the written channel stays continuous
    (and equals the continuous theta), and the metrics do not see the jump."""
    from neuromotor.studies import metrics as mx

    arrays = dict(np.load(dotted["npz"], allow_pickle=False))
    theta = arrays["theta"].copy()
    jumped = theta.copy()
    half = len(theta) // 2
    jumped[half:, 2] += 2 * np.pi
    jumped[: half // 2, 4] -= 2 * np.pi  # a whole-turn offset at the start, too
    arrays["theta"] = jumped
    bad = save_npz_atomic(dotted["dir"] / "jumped.npz", arrays)
    out = export_bvh(bad, dotted["dir"] / "jumped.bvh")
    back = reread_angles(out, float(str(arrays["source_units"])), arrays["dof_names"])
    np.testing.assert_allclose(back, theta, atol=1e-7)
    assert np.abs(np.diff(back, axis=0)).max() < 1.0
    dev_jumped = np.asarray(mx.deviation(jumped, arrays["theta_unperturbed"]))
    dev = np.asarray(mx.deviation(theta, arrays["theta_unperturbed"]))
    np.testing.assert_allclose(dev_jumped, dev, atol=1e-9)


def test_run_npz_provenance(dotted):
    arrays = dict(np.load(dotted["npz"], allow_pickle=False))
    prov = json.loads(str(arrays["provenance_json"]))
    from neuromotor import __version__

    assert prov["neuromotor_version"] == __version__
    clip = dotted["clip"]
    assert prov["clip"]["path"] == str(clip.resolve())
    assert prov["clip"]["sha256"] == hashlib.sha256(clip.read_bytes()).hexdigest()
    cfg = dotted["setup"].config
    assert prov["gains"] == {"ks": cfg.ks, "kd": cfg.kd, "tau_floor": cfg.tau_floor}
    assert prov["h"] == cfg.h and prov["start"] == 0.0
    assert prov["duration"] == pytest.approx(0.3)
    (p,) = prov["perturbations"]
    body_names = list(dotted["setup"].model.body_names)
    assert p["body_requested"] == "chest" and p["body"] in body_names and "." in p["body"]
    assert len(p["point"]) == 3 and not p["point_given"]
    assert p["magnitude"] == 150.0 and p["shape"] == "half_sine"
    assert prov["units"]["length_scale"] == pytest.approx(1.0)
    assert prov["up_axis"]["resolved"] == int(arrays["up_axis"])
    assert prov["stature"]["resolved"] > 1.0
    assert prov["body_mass"]["total"] > 10.0
    for key in ("sex", "simulate_extremities", "ball"):
        assert key in prov


def test_info_command(dotted, capsys):
    assert cli.main(["info", str(dotted["npz"])]) == 0
    out = capsys.readouterr().out
    sha = hashlib.sha256(dotted["clip"].read_bytes()).hexdigest()
    assert sha in out and "gains.ks" in out and "perturbations[0].body" in out
    assert "peak_deviation_deg" in out
    assert cli.main(["info", str(dotted["npz"]), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["provenance"]["clip"]["sha256"] == sha
    assert "peak_deviation_deg" in info["metrics"]


@pytest.mark.parametrize("kind", ["text", "missing", "directory", "not_a_run"])
def test_info_bad_file_is_one_line_exit_2(kind, tmp_path, capsys):
    path = tmp_path / "bad.npz"
    if kind == "text":
        path.write_text("hello")
    elif kind == "directory":
        path.mkdir()
    elif kind == "not_a_run":
        np.savez(path, x=np.zeros(3))
    assert cli.main(["info", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(path) in err and err.startswith("neuromotor info: error:")


def _cfg(dotted) -> str:
    path = dotted["dir"] / "short.toml"
    path.write_text(f'''clip = {json.dumps(str(dotted["clip"]))}
[sim]
duration = 0.3
[[perturbation]]
kind = "force"
body = "chest"
direction = [0.0, 0.0, 1.0]
magnitude = 150.0
start = 0.1
duration = 0.1
shape = "half_sine"
''')
    return str(path)


def test_cli_simulate_progress_lines_and_quiet(dotted, capsys, monkeypatch):
    monkeypatch.setenv("NEUROMOTOR_PROGRESS", "1")  # as on a terminal
    out = dotted["dir"] / "cli_run.npz"
    assert cli.main(["simulate", _cfg(dotted), "-o", str(out)]) == 0
    err = capsys.readouterr().err.splitlines()
    stages = [line for line in err if line.startswith("neuromotor simulate: [")]
    assert len(stages) == 4
    for word, line in zip(("loading clip", "inverse dynamics", "simulating 36 steps", "writing"), stages):
        assert word in line
    # Same run as the Python API, and the provenance names the config file.
    arrays = np.load(out)
    np.testing.assert_allclose(arrays["theta"], dotted["arrays"]["theta"], atol=1e-12)
    assert json.loads(str(arrays["provenance_json"]))["config_source"].endswith("short.toml")
    assert cli.main(["simulate", _cfg(dotted), "-o", str(out), "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_cli_idyn_and_render_progress(dotted, capsys, monkeypatch):
    monkeypatch.setenv("NEUROMOTOR_PROGRESS", "1")  # as on a terminal
    out = dotted["dir"] / "idyn.npz"
    assert cli.main(["idyn", str(dotted["clip"]), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert err.count("neuromotor idyn: [") == 3 and "inverse dynamics of 40 frames" in err
    assert cli.main(["idyn", str(dotted["clip"]), "-o", str(out), "--quiet"]) == 0
    assert capsys.readouterr().err == ""
    png = dotted["dir"] / "strip.png"
    assert cli.main(["render", str(dotted["npz"]), "-o", str(png), "--frames", "3"]) == 0
    err = capsys.readouterr().err
    assert err.count("neuromotor render: [") == 3 and "3-panel filmstrip" in err and png.exists()
    assert cli.main(["render", str(dotted["npz"]), "-o", str(png), "--frames", "3", "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_progress_lines_not_in_captured_stderr_by_default(dotted, capsys, monkeypatch):
    """Not a terminal (a script, CI): stderr keeps only warnings and errors (a failing command's
    stderr stays one line)."""
    monkeypatch.delenv("NEUROMOTOR_PROGRESS", raising=False)
    assert cli.main(["idyn", str(dotted["clip"]), "-o", str(dotted["dir"] / "i2.npz")]) == 0
    assert capsys.readouterr().err == ""
    assert cli.main(["idyn", str(dotted["dir"]), "-o", str(dotted["dir"] / "i3.npz")]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
