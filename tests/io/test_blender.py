"""Blender as a real client: Debian's ``blender`` (3.4, installed by .ci/install_system_deps.sh),
headless, imports our ``.glb`` and ``.bvh`` with its own importers, as File > Import does, and
what it made of them is compared with RUN.npz: bone count and names, frame range and rate, every
bone's world position (1 mm) and rotation (0.1 deg) at several frames, and a rendered frame that
is not blank. One Blender process checks every file of a module (tests/io/blender_check.py).

Without ``blender`` on the path the tests fail (the install command provides it);
``NEUROMOTOR_SKIP_BLENDER=1`` turns that into a skip.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import imageio.v3 as iio
import numpy as np
import pytest

from conftest import ALL_CLIPS
from neuromotor.config import DEFAULT_HIT, SimulationConfig
from neuromotor.io.export import export_bvh
from neuromotor.io.gltf import export_gltf
from neuromotor.io.runfile import write_run
from neuromotor.model.bvh import read_bvh
from neuromotor.studies.record import run_arrays
from neuromotor.studies.simulate import load_character, prepare, run

BLENDER = os.environ.get("NEUROMOTOR_BLENDER") or shutil.which("blender")
CHECK = os.path.join(os.path.dirname(__file__), "blender_check.py")
POS_TOL_M, ROT_TOL_DEG = 1e-3, 0.1

# Blender is Z up, forward -Y. Its importers turn a Y-up file by (x, y, z) -> (x, -z, y) (glTF
# always; BVH with its default Up = Y, Forward = -Z) and leave a Z-up BVH alone (Up = Z, Forward = Y).
BLENDER_FROM = {1: np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), 2: np.eye(3)}
# glTF is Y up: our exporter turns a Z-up clip by (x, y, z) -> (x, z, -y) (docs/gltf.md).
GLTF_FROM = {1: np.eye(3), 2: np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])}
BVH_AXES = {1: ("Y", "-Z"), 2: ("Z", "Y")}


def _need_blender():
    if BLENDER is None:
        message = "blender not found (Debian package blender; bash .ci/install installs it)"
        if os.environ.get("NEUROMOTOR_SKIP_BLENDER") == "1":
            pytest.skip(message + "; NEUROMOTOR_SKIP_BLENDER=1")
        pytest.fail(message + "; NEUROMOTOR_SKIP_BLENDER=1 skips")


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) w x y z -> (..., 3, 3), written out here independently of the package."""
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle of the rotation a^T b, degrees."""
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _make_run(folder, clip=None, start=0.8, duration=0.45, h=1.0 / 120.0, hit=None):
    """A short window around a hit (by default the README example's: the default clip, the
    default hit at 300 N, 0.8 to 1.25 s), written as RUN.npz, .glb and .bvh."""
    folder.mkdir(parents=True, exist_ok=True)
    hit = dict(DEFAULT_HIT, magnitude=300.0, **(hit or {}))
    cfg = SimulationConfig(clip=clip, start=start, duration=duration, h=h, perturbations=[hit])
    setup = prepare(cfg)
    path = folder / "run.npz"
    write_run(path, run_arrays(setup, run(setup)))
    export_gltf(path, folder / "run.glb")
    export_bvh(path, folder / "run.bvh")
    return folder


def _npz(folder) -> dict:
    with np.load(folder / "run.npz") as f:
        return {k: f[k] for k in f.files}


def _frames(T: int) -> list[int]:
    return sorted({0, T // 3, (2 * T) // 3, T - 1})


def _blender(folders, tmp, render_first=True) -> dict:
    """One Blender process over the .glb and .bvh of every folder: {(folder, kind): result}."""
    _need_blender()
    jobs = []
    for i, folder in enumerate(folders):
        d = _npz(folder)
        up, frames = int(d["up_axis"]), _frames(len(d["time"]))
        if up not in BVH_AXES:
            raise AssertionError(f"no Blender axis setting written down for up axis {up}")
        jobs.append(dict(kind="glb", path=str(folder / "run.glb"), fps=round(1 / (d["time"][1] - d["time"][0])),
                         frames=frames, out=str(tmp / f"{i}_glb.json"),
                         render=str(tmp / f"{i}.png") if render_first and i == 0 else None))
        axis_up, axis_forward = BVH_AXES[up]
        jobs.append(dict(kind="bvh", path=str(folder / "run.bvh"), scale=float(d["source_units"]),
                         axis_up=axis_up, axis_forward=axis_forward, frames=[f + 1 for f in frames],
                         out=str(tmp / f"{i}_bvh.json")))
    (tmp / "jobs.json").write_text(json.dumps(jobs))
    out = subprocess.run([BLENDER, "-b", "--factory-startup", "-noaudio", "--python-exit-code", "1",
                          "--python", CHECK, "--", str(tmp / "jobs.json")],
                         capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0 and "blender_check: done" in out.stdout, out.stdout[-3000:] + out.stderr[-3000:]
    return {(folder, kind): json.loads((tmp / f"{i}_{kind}.json").read_text())
            for i, folder in enumerate(folders) for kind in ("glb", "bvh")}


def check_glb(folder, got):
    """The character's armature: one bone per body, named after it, each bone's head on the
    body's COM and its axes the body's axes at every checked frame (the importer's bone
    heuristic leaves a bone without children on its node's +Y: no extra roll); the ghost's
    armature the same with the unperturbed poses; keyframes on frames 0 .. T-1 at the run's rate."""
    d = _npz(folder)
    T, names = len(d["time"]), [str(n) for n in d["body_names"]]
    up = int(d["up_axis"])
    M = BLENDER_FROM[1] @ GLTF_FROM[up]
    assert got["blender"].startswith("3.4")
    assert got["fps"] == pytest.approx(1 / (d["time"][1] - d["time"][0]), rel=1e-9)
    assert got["actions"] == ["perturbed_root", "unperturbed_ghost_root"]
    assert got["meshes"] == ["character", "ghost"]
    arms = got["armatures"]
    assert sorted(arms) == ["ghost_root", "root"]
    assert arms["root"]["bones"] == names and arms["ghost_root"]["bones"] == ["ghost_" + n for n in names]
    assert arms["root"]["action"] == "perturbed_root"
    assert arms["root"]["action_range"] == pytest.approx([0.0, T - 1.0], abs=1e-4)   # float32 times x fps
    assert arms["root"]["tracks"] == ["perturbed"] and arms["ghost_root"]["tracks"] == ["unperturbed"]
    frames = _frames(T)
    worst = [0.0, 0.0]
    # The ghost has no active action after import (its motion is in its NLA track): Blender
    # shows it in the rest pose, which is the first frame's pose (docs/gltf.md).
    for arm, prefix, suffix, ks in (("root", "", "", frames), ("ghost_root", "ghost_", "_unperturbed", [0] * len(frames))):
        pos, R = d["body_pos" + suffix], _quat_matrix(d["body_quat" + suffix])
        for pose, k in zip(arms[arm]["pose"], ks):
            for b, name in enumerate(names):
                bone = pose[prefix + name]
                worst[0] = max(worst[0], float(np.linalg.norm(np.array(bone["head"]) - M @ pos[k, b])))
                worst[1] = max(worst[1], _angle_deg(M @ R[k, b] @ M.T, np.array(bone["rot"])))
    assert worst[0] < POS_TOL_M and worst[1] < ROT_TOL_DEG, worst
    return worst


def check_bvh(folder, got):
    """The BVH's armature: one bone per joint of the file, named after it; the scene's rate
    1 / h and the action on frames 1 .. T; each joint's world position (RUN.npz
    ``skeleton_points``) at every checked frame, and each simulated body's rotation: the rest
    bone (pointing at its child, with the importer's roll) turned by the body's rotation."""
    d = _npz(folder)
    T, up = len(d["time"]), int(d["up_axis"])
    M = BLENDER_FROM[up]
    file_joints = [j.name for j in read_bvh(folder / "run.bvh", units=float(d["source_units"])).joints]
    character, _ = load_character(str(d["source_clip"]), float(d["source_units"]), up)
    model_joints = list(character.model.joint_names)
    arm = got["armatures"]["run"]
    assert arm["bones"] == file_joints and arm["action"] == "run"
    assert got["fps"] == pytest.approx(1 / (d["time"][1] - d["time"][0]), rel=1e-6)
    assert arm["action_range"] == pytest.approx([1.0, float(T)], abs=1e-9)
    R = _quat_matrix(d["body_quat"])
    bodies = [str(n) for n in d["body_names"]]
    worst = [0.0, 0.0]
    for pose, k in zip(arm["pose"], _frames(T)):
        for j, name in enumerate(model_joints):
            head = np.array(pose[name]["head"])
            worst[0] = max(worst[0], float(np.linalg.norm(head - M @ d["skeleton_points"][k, j])))
        for b, name in enumerate(bodies):
            rest = np.array(arm["rest"][name]["rot"])
            worst[1] = max(worst[1], _angle_deg(M @ R[k, b] @ M.T @ rest, np.array(pose[name]["rot"])))
    assert worst[0] < POS_TOL_M and worst[1] < ROT_TOL_DEG, worst
    return worst


def check_render(png):
    """Not blank: the orange character covers part of the frame and the picture varies."""
    img = iio.imread(png)[..., :3].astype(float)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    orange = (r > 1.3 * g) & (g > 1.2 * b) & (r > 60)
    assert img.std() > 8.0 and orange.mean() > 0.01, (img.std(), orange.mean())


# ------------------------------------------------------------------ the default clip (default run)

@pytest.fixture(scope="module")
def default_clip(tmp_path_factory):
    _need_blender()
    folder = _make_run(tmp_path_factory.mktemp("blender") / "default")
    tmp = tmp_path_factory.mktemp("blender_out")
    return folder, tmp, _blender([folder], tmp)


def test_blender_imports_our_glb(default_clip):
    folder, _, got = default_clip
    check_glb(folder, got[(folder, "glb")])


def test_blender_imports_our_bvh(default_clip):
    folder, _, got = default_clip
    check_bvh(folder, got[(folder, "bvh")])


def test_blender_renders_our_glb(default_clip):
    _, tmp, _ = default_clip
    check_render(tmp / "0.png")


def test_a_wrong_pose_is_caught(default_clip):
    """The checks can fail: a 2 mm shift of one body or a 0.2 deg turn of one bone is reported."""
    folder, _, got = default_clip
    shifted = json.loads(json.dumps(got[(folder, "glb")]))
    shifted["armatures"]["root"]["pose"][1]["Chest"]["head"][2] += 2e-3
    with pytest.raises(AssertionError):
        check_glb(folder, shifted)
    turned = json.loads(json.dumps(got[(folder, "bvh")]))
    c, s = np.cos(np.radians(0.2)), np.sin(np.radians(0.2))
    rot = np.array(turned["armatures"]["run"]["pose"][2]["LeftElbow"]["rot"])
    turned["armatures"]["run"]["pose"][2]["LeftElbow"]["rot"] = (rot @ [[c, -s, 0], [s, c, 0], [0, 0, 1]]).tolist()
    with pytest.raises(AssertionError):
        check_bvh(folder, turned)


# ------------------------------------------------------------------ every shipped clip (extended)

# The Bandai-Namco kick spins fast: the step its replay needs (tests/studies/test_every_clip.py).
CLIP_STEP = {"bandai_kick_22joint_6ch": 1.0 / 360.0}


@pytest.mark.extended
def test_blender_imports_every_shipped_clip(tmp_path):
    _need_blender()
    folders = [_make_run(tmp_path / name, clip=str(path), start=0.5, duration=0.3, h=CLIP_STEP.get(name, 1 / 120),
                         hit=dict(body="chest", start=0.6)) for name, path in ALL_CLIPS.items()]
    got = _blender(folders, tmp_path, render_first=False)
    for folder in folders:
        check_glb(folder, got[(folder, "glb")])
        check_bvh(folder, got[(folder, "bvh")])
