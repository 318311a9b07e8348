"""glTF 2.0 export (neuromotor.io.gltf), checked by its consumers: the Khronos validator accepts
the files, pygltflib reads back the body poses of RUN.npz in glTF's Y-up frame to 1e-6 (float32
rounding), and three.js plays them to the same vertex positions. A small synthetic RUN.npz (three
boxes, Z up with a ball, Y up without) keeps it quick; docs/gltf.md has the figures on a real run."""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neuromotor.cli import main
from neuromotor.io.gltf import Layout, body_colors, body_side, export_gltf, y_up_poses
from neuromotor.io.runfile import write_run

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCRIPT = pathlib.Path(__file__).with_name("validate_gltf.cjs")
# Clip coordinates -> glTF coordinates, written out independently of the exporter.
TO_Y_UP = {1: np.eye(3), 2: np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
           0: np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])}
HEIGHT = 1.8  # the synthetic figure's extent along its up axis (m)
T, B = 40, 3


def _missing(what: str):
    """Skip locally, fail under CI: a format check must never be skipped there silently."""
    (pytest.fail if os.environ.get("CI") else pytest.skip)(what)


def _node_or_skip(package: str) -> str:
    node = shutil.which("node")
    if node is None or not (ROOT / "node_modules" / package).is_dir():
        _missing(f"node or node_modules/{package} missing (run .ci/install: npm ci)")
    return node


def _box(half) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float) * half
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def synthetic_run(path, up_axis: int, ball: bool) -> dict:
    """Three stacked boxes (legs, trunk, head) swaying about the up axis, HEIGHT tall, COMs
    offset from the box centres; the unperturbed run sways less."""
    rng = np.random.default_rng(up_axis)
    time = 0.25 + np.arange(T) / 60.0
    up = np.eye(3)[up_axis]
    side = np.eye(3)[(up_axis + 1) % 3]
    halves = [0.15 + (0.45 - 0.15) * up, 0.15 + (0.3 - 0.15) * up, 0.1 + (0.15 - 0.1) * up]
    centres = [0.45, 0.9 + 0.3, 1.5 + 0.15]  # boxes span 0..0.9, 0.9..1.5, 1.5..1.8 along up
    com_off = [0.02 * side, -0.03 * up, 0.01 * side]
    verts, faces, owner = [], [], []
    for b in range(B):
        v, f = _box(halves[b])
        faces.append(f + 8 * b)
        verts.append(v - com_off[b])  # body frame less the COM
        owner.append(np.full(8, b))
    base = np.array([0.3, -0.2, 0.1]) * (1 - up)  # feet at 0 along up

    def poses(amp):
        ang = amp * np.sin(2 * np.pi * 1.3 * (time - time[0]))[:, None] * (1 + np.arange(B))[None]
        rot = Rotation.from_rotvec((ang[..., None] * up).reshape(-1, 3)) * \
            Rotation.from_rotvec(np.tile(rng.normal(0, 0.05, (1, B, 3)), (T, 1, 1)).reshape(-1, 3))
        q_xyzw = rot.as_quat().reshape(T, B, 4)
        pos = base + np.array(centres)[None, :, None] * up + np.einsum(
            "tbij,bj->tbi", rot.as_matrix().reshape(T, B, 3, 3), np.array(com_off))
        pos = pos + 0.05 * (time - time[0])[:, None, None] * side
        return pos, np.concatenate([q_xyzw[..., 3:], q_xyzw[..., :3]], -1)  # w x y z

    pos, quat = poses(0.4)
    quat[::3, 1] *= -1  # RUN.npz may hold either sign of a quaternion
    pos_u, quat_u = poses(0.1)
    d = {"time": time, "theta": np.zeros((T, 1)), "up_axis": np.asarray(up_axis),
         "body_names": np.array(["Legs", "Trunk", "Head"]),
         "shape_vertices": np.concatenate(verts), "shape_faces": np.concatenate(faces),
         "shape_body": np.concatenate(owner), "body_pos": pos, "body_quat": quat,
         "body_pos_unperturbed": pos_u, "body_quat_unperturbed": quat_u}
    if ball:
        d["ball_pos"] = base + 1.2 * up + side * np.linspace(2.0, 0.2, T)[:, None]
        d["ball_radius"] = np.asarray(0.11)
    write_run(path, d)
    return d


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """(RUN.npz arrays, exported file, layout) for a Z-up run with a ball (GLB, ghost) and a Y-up
    run without one (.gltf, shared)."""
    d = tmp_path_factory.mktemp("gltf")
    out = {}
    for key, up, ball, name, layout in (("z", 2, True, "z.glb", Layout.GHOST),
                                       ("y", 1, False, "y.gltf", Layout.SHARED)):
        arrays = synthetic_run(d / f"{key}.npz", up, ball)
        out[key] = (arrays, export_gltf(d / f"{key}.npz", d / name, layout), layout)
    return out


def _load(path):
    pygltflib = pytest.importorskip("pygltflib")
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob() if str(path).endswith(".glb") else g.decode_data_uri(g.buffers[0].uri)
    return g, blob


def _read(g, blob, index: int) -> np.ndarray:
    """An accessor's values (float32, uint8/16/32), shaped (count, width)."""
    acc = g.accessors[index]
    view = g.bufferViews[acc.bufferView]
    dtype = {5126: np.float32, 5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(blob, dtype, acc.count * width, start).reshape(acc.count, width).astype(np.float64)


def _tracks(g, blob, name: str) -> dict:
    """{(node name, path): (times, values)} of the animation ``name``."""
    anim = next(a for a in g.animations if a.name == name)
    out = {}
    for ch in anim.channels:
        s = anim.samplers[ch.sampler]
        assert s.interpolation == "LINEAR"
        out[(g.nodes[ch.target.node].name, ch.target.path)] = (_read(g, blob, s.input)[:, 0],
                                                               _read(g, blob, s.output))
    return out


# ----------------------------------------------------------------------------------------------

def test_khronos_validator_reports_no_errors(runs, tmp_path):
    node = _node_or_skip("gltf-validator")
    # A broken copy (a node pointing at a mesh that does not exist) must be caught: the
    # validator really runs.
    doc = json.loads(runs["y"][1].read_text())
    doc["nodes"][0]["mesh"] = 99
    broken = tmp_path / "broken.gltf"
    broken.write_text(json.dumps(doc))
    files = [runs["z"][1], runs["y"][1], broken]
    proc = subprocess.run([node, str(SCRIPT), *map(str, files)], cwd=ROOT, capture_output=True, text=True, check=False,
                          timeout=120)
    reports = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(reports) == 3, proc.stderr
    for r in reports[:2]:
        print(f"{r['file']}: {r['numWarnings']} warnings, {r['numInfos']} infos: "
              f"{[m['code'] for m in r['messages']]}")
        assert r["numErrors"] == 0, r["messages"]
        assert r["info"]["animationCount"] == 2 and r["info"]["hasSkins"]
    assert reports[2]["numErrors"] > 0 and proc.returncode == 1


@pytest.mark.parametrize("key", ["z", "y"])
def test_keyframes_are_the_runs_body_poses_in_y_up(runs, key):
    d, path, layout = runs[key]
    g, blob = _load(path)
    M = TO_Y_UP[int(d["up_axis"])]
    prefix = {"perturbed": "", "unperturbed": "ghost_" if layout is Layout.GHOST else ""}
    for anim, suffix in (("perturbed", ""), ("unperturbed", "_unperturbed")):
        tracks = _tracks(g, blob, anim)
        for b, name in enumerate(d["body_names"]):
            t, xyz = tracks[(prefix[anim] + name, "translation")]
            t_r, q = tracks[(prefix[anim] + name, "rotation")]
            np.testing.assert_allclose(t, d["time"] - d["time"][0], rtol=0, atol=1e-6)
            np.testing.assert_array_equal(t, t_r)
            np.testing.assert_allclose(xyz, d["body_pos" + suffix][:, b] @ M.T, rtol=0, atol=1e-6)
            w_xyz = d["body_quat" + suffix][:, b]
            want = Rotation.from_matrix(M) * Rotation.from_quat(np.c_[w_xyz[:, 1:], w_xyz[:, :1]])
            want = want.as_quat() * np.sign(np.sum(q * want.as_quat(), axis=1))[:, None]  # q ~ -q
            np.testing.assert_allclose(q, want, rtol=0, atol=1e-6)  # x y z w
            assert np.all(np.sum(q[1:] * q[:-1], axis=1) > 0)  # no sign flips: LINEAR takes the short way
    # Nothing else is animated: 2 channels per body (+ the ball's translation).
    assert len(_tracks(g, blob, "perturbed")) == 2 * B + ("ball_pos" in d)


@pytest.mark.parametrize("up_axis", [0, 1, 2])
def test_axis_change_is_a_proper_rotation_taking_up_to_y(up_axis):
    p = np.random.default_rng(0).normal(size=(5, 3))
    rot = Rotation.random(5, random_state=1)
    q = rot.as_quat()
    pos, quat = y_up_poses(p, np.c_[q[:, 3:], q[:, :3]], up_axis)
    M = TO_Y_UP[up_axis]
    assert np.allclose(M @ np.eye(3)[up_axis], [0, 1, 0]) and np.isclose(np.linalg.det(M), 1)
    got = Rotation.from_quat(np.c_[quat[:, 1:], quat[:, :1]])
    assert np.allclose((got * (Rotation.from_matrix(M) * rot).inv()).magnitude(), 0, atol=1e-12)
    np.testing.assert_allclose(pos, p @ M.T, rtol=0, atol=1e-15)


def _skinned_world(g, blob, frame: int) -> np.ndarray:
    """World vertices of the character at ``frame``: joint pose from the perturbed keyframes,
    times the inverse bind matrix, times POSITION (glTF's skinning with weight 1)."""
    tracks = _tracks(g, blob, "perturbed")
    skin = g.skins[0]
    prim = g.meshes[g.nodes[next(i for i, n in enumerate(g.nodes) if n.skin == 0)].mesh].primitives[0]
    pos = _read(g, blob, prim.attributes.POSITION)
    joint = _read(g, blob, prim.attributes.JOINTS_0)[:, 0].astype(int)
    ibm = _read(g, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    out = np.zeros_like(pos)
    for j, node in enumerate(skin.joints):
        name = g.nodes[node].name
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(tracks[(name, "rotation")][1][frame]).as_matrix()
        m[:3, 3] = tracks[(name, "translation")][1][frame]
        v = np.c_[pos[joint == j], np.ones((joint == j).sum())]
        out[joint == j] = (v @ (m @ ibm[j]).T)[:, :3]
    return out


@pytest.mark.parametrize("key", ["z", "y"])
def test_skinned_mesh_is_the_runs_bodies_in_metres_y_up(runs, key):
    d, path, _ = runs[key]
    g, blob = _load(path)
    M = TO_Y_UP[int(d["up_axis"])]
    v, owner = d["shape_vertices"], d["shape_body"]
    for frame in (0, T // 2, T - 1):
        rot = Rotation.from_quat(np.c_[d["body_quat"][frame, :, 1:], d["body_quat"][frame, :, :1]]).as_matrix()
        want = (d["body_pos"][frame, owner] + np.einsum("vij,vj->vi", rot[owner], v)) @ M.T
        got = _skinned_world(g, blob, frame)
        assert got.shape == v.shape  # one glTF vertex per RUN.npz vertex
        np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)
        # Metres, and the clip's up is +Y: the figure stands HEIGHT tall along Y, feet near 0.
        assert abs(np.ptp(got[:, 1]) - HEIGHT) < 0.05
        assert abs(got[:, 1].min()) < 0.05
    # The scene's root nodes carry no rotation: the Y-up change is in the keyframes.
    g_roots = [g.nodes[i] for i in g.scenes[g.scene].nodes]
    assert all(n.rotation in (None, [0, 0, 0, 1]) for n in g_roots)
    assert g.scenes[g.scene].extras["source_up_axis"] == int(d["up_axis"])


@pytest.mark.parametrize("anim, mesh, suffix", [("perturbed", "character", ""),
                                                ("unperturbed", "ghost", "_unperturbed")])
def test_three_js_plays_the_runs_motion(runs, anim, mesh, suffix):
    """three.js's GLTFLoader and AnimationMixer, at a keyframe time, put every skinned vertex
    where RUN.npz's body pose puts it (Y up)."""
    node = _node_or_skip("three")
    d, path, _ = runs["z"]
    k = T // 3
    proc = subprocess.run([node, str(SCRIPT.with_name("three_gltf_pose.mjs")), str(path), anim,
                           repr(float(d["time"][k] - d["time"][0])), mesh],
                          cwd=ROOT, capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout)
    assert [c[0] for c in report["clips"]] == ["perturbed", "unperturbed"]
    assert np.isclose(report["clips"][0][1], d["time"][-1] - d["time"][0], atol=1e-6)
    w_xyz = d["body_quat" + suffix][k]
    rot = Rotation.from_quat(np.c_[w_xyz[:, 1:], w_xyz[:, :1]]).as_matrix()
    owner = d["shape_body"]
    want = (d["body_pos" + suffix][k, owner] + np.einsum("vij,vj->vi", rot[owner], d["shape_vertices"])) @ TO_Y_UP[2].T
    np.testing.assert_allclose(np.array(report["vertices"]), want, rtol=0, atol=2e-6)


def test_layouts_materials_and_ball(runs):
    g, blob = _load(runs["z"][1])
    names = [n.name for n in g.nodes]
    assert "ghost" in names and len(g.skins) == 2
    ghost_mat = next(m for m in g.materials if m.name == "ghost")
    assert ghost_mat.alphaMode == "BLEND" and ghost_mat.pbrMetallicRoughness.baseColorFactor[3] < 1
    body_mats = {m.name for m in g.materials} & set(runs["z"][0]["body_names"])
    assert len(body_mats) == B  # a colour per body
    _, ball = _tracks(g, blob, "perturbed")[("ball", "translation")]
    np.testing.assert_allclose(ball, runs["z"][0]["ball_pos"] @ TO_Y_UP[2].T, rtol=0, atol=1e-6)
    ball_pos = _read(g, blob, g.meshes[g.nodes[names.index("ball")].mesh].primitives[0].attributes.POSITION)
    np.testing.assert_allclose(np.linalg.norm(ball_pos, axis=1), 0.11, atol=1e-6)
    g, blob = _load(runs["y"][1])  # shared: both animations drive the same joints
    assert len(g.skins) == 1 and "ghost" not in [n.name for n in g.nodes]
    assert set(_tracks(g, blob, "perturbed")) == set(_tracks(g, blob, "unperturbed"))


def test_left_and_right_bodies_get_lighter_and_darker_colours():
    names = ["Hips", "LeftArm", "mixamorig:RightLeg", "L_Hip", "lShldr", "hip.R", "LowerBack", "rfemur"]
    assert [body_side(n) for n in names] == [0, 1, -1, 1, 1, -1, 0, 0]
    rgb = body_colors(["LeftArm", "Chest", "RightArm"]).sum(axis=1)
    assert rgb[0] > rgb[1] > rgb[2]


# ----------------------------------------------------------------------------------------------
# Command line
# ----------------------------------------------------------------------------------------------

def test_cli_writes_a_glb(runs, tmp_path, capsys):
    out = tmp_path / "run.glb"
    run = runs["z"][1].with_name("z.npz")
    assert main(["export-gltf", str(run), "-o", str(out)]) == 0
    data = out.read_bytes()
    assert data[:4] == b"glTF" and int.from_bytes(data[8:12], "little") == len(data)
    assert data == runs["z"][1].read_bytes()  # same bytes as the library call
    assert f"wrote {out}" in capsys.readouterr().out


def test_cli_bad_input_exits_2_naming_file_and_field(tmp_path, capsys):
    out = tmp_path / "run.glb"
    assert main(["export-gltf", str(tmp_path / "nope.npz"), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nope.npz" in err
    no_shapes = write_run(tmp_path / "bare.npz", {"time": np.arange(3.0), "theta": np.zeros((3, 1))})
    assert main(["export-gltf", str(no_shapes), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bare.npz" in err and "shape_vertices" in err
    assert main(["export-gltf", str(no_shapes), "-o", str(tmp_path / "run.obj")]) == 2
    assert "run.obj" in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "run.obj").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["bare.npz"]  # no temporary left either
