"""Rendering: filmstrip PNG, MP4/GIF video and plots, on a synthetic run and one short real run."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from neuromotor.viz import render
from neuromotor.viz.camera import set_camera
from neuromotor.viz.geometry import FigureGeometry
from neuromotor.viz.scene import Scene
from neuromotor.viz.render import RenderError, plot_run, render_run

HIT_START, HIT_DURATION = 0.3, 0.1


# ------------------------------------------------------------------ synthetic run (no simulation)

_NAMES = ["Hips", "Spine", "Neck", "Head_end", "LShoulder", "LElbow", "LHand_end", "RShoulder",
          "RElbow", "RHand_end", "LHip", "LKnee", "LAnkle", "LToe_end", "RHip", "RKnee", "RAnkle",
          "RToe_end"]
_REST = np.array([
    [0, 1.00, 0], [0, 1.30, 0], [0, 1.55, 0], [0, 1.78, 0],
    [0, 1.48, 0.18], [0, 1.22, 0.24], [0, 0.98, 0.26],
    [0, 1.48, -0.18], [0, 1.22, -0.24], [0, 0.98, -0.26],
    [0, 0.95, 0.10], [0, 0.52, 0.10], [0, 0.09, 0.10], [0.16, 0.02, 0.10],
    [0, 0.95, -0.10], [0, 0.52, -0.10], [0, 0.09, -0.10], [0.16, 0.02, -0.10]], float)
_EDGES = np.array([[0, 1], [1, 2], [2, 3], [2, 4], [4, 5], [5, 6], [2, 7], [7, 8], [8, 9],
                   [0, 10], [10, 11], [11, 12], [12, 13], [0, 14], [14, 15], [15, 16], [16, 17]])
_UPPER = np.arange(1, 10)   # points that lean when hit


def synthetic_run(duration=1.0, h=1 / 120, magnitude=300.0, with_ball=False, shift=0.0,
                  with_bodies=False) -> dict:
    """A stick figure swinging its arms, hit at the chest along +z at HIT_START: the upper body
    leans away (rotation about the hips) and recovers."""
    t = np.arange(int(round(duration / h)) + 1) * h
    T = len(t)
    base = np.repeat(_REST[None], T, axis=0)
    swing = 0.15 * np.sin(2 * np.pi * t)                       # arms swing fore-aft (x)
    base[:, [5, 6], 0] += swing[:, None]
    base[:, [8, 9], 0] -= swing[:, None]
    base[:, :, 0] += shift
    s = np.clip((t - HIT_START) / 0.15, 0, None)
    lean = 0.45 * s * np.exp(1 - s)                            # rad, peaks 0.15 s after the hit
    pert = base.copy()
    hip = base[:, 0]
    rel = base[:, _UPPER] - hip[:, None]
    c, sn = np.cos(lean)[:, None], np.sin(lean)[:, None]
    y, z = rel[..., 1], rel[..., 2]
    pert[:, _UPPER, 1] = hip[:, None, 1] + c * y - sn * z
    pert[:, _UPPER, 2] = hip[:, None, 2] + sn * y + c * z
    on = (t >= HIT_START) & (t < HIT_START + HIT_DURATION)
    fmag = np.where(on, magnitude * np.sin(np.pi * (t - HIT_START) / HIT_DURATION), 0.0)
    force = np.zeros((T, 3))
    force[:, 2] = fmag
    n_dof = 6
    theta_u = 0.3 * np.sin(2 * np.pi * t[:, None] + np.arange(n_dof))
    theta = theta_u + lean[:, None] * np.linspace(1.0, 0.1, n_dof)
    d = {
        "time": t,
        "skeleton_points": pert,
        "skeleton_points_unperturbed": base,
        "skeleton_edges": _EDGES,
        "skeleton_radii": np.full(len(_EDGES), 0.035),
        "force_origin": pert[:, 2],
        "force_vector": force,
        "perturbation_force": force[:, None, :],
        "up_axis": np.asarray(1),
        "dof_names": np.array([f"J{i}.rot{'xyz'[i % 3]}" for i in range(n_dof)]),
        "theta": theta,
        "theta_unperturbed": theta_u,
        "theta_desired": theta_u + 0.01,
        "metrics_json": np.asarray(json.dumps({"peak_deviation_deg": 25.0, "time_of_peak_s": 0.45,
                                                  "recovery_time_s": 0.5, "recovery_threshold_deg": 0.5})),
    }
    if with_ball:
        p0, v = np.array([0.0, 1.5, -1.2]), np.array([0.0, 0.0, 4.0])
        d["ball_pos"] = p0 + v * (t - HIT_START)[:, None] - np.array([0.0, 0.11, 0.0])
        d["ball_radius"] = np.asarray(0.11)
    if with_bodies:
        _add_bodies(d, lean)
    return d


_BOX_R = 0.045
_TOE_EDGES = [12, 16]   # edges (ankle, toe): detail without a body, drawn as capsules


def _box(length_vec, r=_BOX_R):
    """Box around the segment 0 -> length_vec, padded by r: (8,3) vertices, (12,3) outward faces."""
    u = length_vec / np.linalg.norm(length_vec)
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    v = np.array([(length_vec + r * u if i else -r * u) + r * (2 * j - 1) * e1 + r * (2 * k - 1) * e2
                  for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = []
    centre = v.mean(axis=0)
    for a, b, c, d in quads:
        for tri in ((a, b, c), (a, c, d)):
            n = np.cross(v[tri[1]] - v[tri[0]], v[tri[2]] - v[tri[0]])
            faces.append(tri if n @ (v[list(tri)].mean(axis=0) - centre) > 0 else tri[::-1])
    return v, np.array(faces)


def _quat_matrix(q):
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _quat_mul(a, b):
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def _add_bodies(d, lean):
    """One box body per bone except the toes (their bones carry no body): the body frame sits at
    the bone's first point, unrotated at rest, and leans with the upper body when hit."""
    T = len(d["time"])
    verts, faces, owner, edge_body, n = [], [], [], [], 0
    pos = {"": np.zeros((T, 0, 3)), "_unperturbed": np.zeros((T, 0, 3))}
    quat = {"": np.zeros((T, 0, 4)), "_unperturbed": np.zeros((T, 0, 4))}
    ident = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
    leaning = np.stack([np.cos(lean / 2), np.sin(lean / 2), 0 * lean, 0 * lean], -1)   # about +x
    for e, (a, b) in enumerate(_EDGES):
        if e in _TOE_EDGES:
            edge_body.append(-1)
            continue
        v, f = _box(_REST[b] - _REST[a])
        com = v.mean(axis=0)
        verts.append(v - com)
        faces.append(f + n)
        owner.append(np.full(len(v), len(edge_body) - edge_body.count(-1)))
        n += len(v)
        for tag, pts, q in (("", d["skeleton_points"], leaning if b in _UPPER else ident),
                            ("_unperturbed", d["skeleton_points_unperturbed"], ident)):
            R = np.stack([_quat_matrix(qq) for qq in q])
            pos[tag] = np.concatenate([pos[tag], (pts[:, a] + R @ com)[:, None]], axis=1)
            quat[tag] = np.concatenate([quat[tag], q[:, None]], axis=1)
        edge_body.append(pos[""].shape[1] - 1)
    d.update(shape_vertices=np.concatenate(verts), shape_faces=np.concatenate(faces),
             shape_body=np.concatenate(owner), skeleton_edge_body=np.array(edge_body),
             body_pos=pos[""], body_quat=quat[""], body_pos_unperturbed=pos["_unperturbed"],
             body_quat_unperturbed=quat["_unperturbed"])


def rotate_run(d, R) -> dict:
    """The run ``d`` with the whole world rotated by R (positions, directions and body poses)."""
    d = dict(d)
    for k in ("skeleton_points", "skeleton_points_unperturbed", "force_origin", "force_vector",
              "ball_pos", "body_pos", "body_pos_unperturbed", "facing"):
        if k in d:
            d[k] = np.asarray(d[k]) @ R.T
    if "perturbation_force" in d:
        d["perturbation_force"] = d["perturbation_force"] @ R.T
    # The quaternion of R (R is a proper rotation), premultiplied onto every body orientation.
    w = np.sqrt(max(1.0 + np.trace(R), 1e-12)) / 2
    if w > 1e-3:
        qr = np.array([w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)])
    else:  # a half turn: no such runs here
        raise ValueError("rotation by pi")
    for k in ("body_quat", "body_quat_unperturbed"):
        if k in d:
            d[k] = _quat_mul(np.broadcast_to(qr, d[k].shape), d[k])
    return d


def _rot_axis(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


Y_TO_Z = _rot_axis([1.0, 0.0, 0.0], np.pi / 2)   # takes +Y to +Z: a Z-up world


def _variants():
    """(name, R, up_axis): the Y-up synthetic run, turned Z-up, and turned by a random heading."""
    heading = float(np.random.default_rng(14).uniform(-np.pi, np.pi))
    return [("y-up", np.eye(3), 1), ("z-up", Y_TO_Z, 2),
            ("heading", _rot_axis([0.0, 1.0, 0.0], heading), 1),
            ("z-up+heading", _rot_axis([0.0, 0.0, 1.0], heading) @ Y_TO_Z, 2)]


def _save(path, arrays):
    np.savez(path, **arrays)
    return path


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    return _save(tmp_path_factory.mktemp("synth") / "run.npz", synthetic_run())


# ------------------------------------------------------------------ one short real run

@pytest.fixture(scope="module")
def real_run(tmp_path_factory):
    from neuromotor.config import DEFAULT_HIT, SimulationConfig
    from neuromotor.studies.record import run_arrays
    from neuromotor.studies.simulate import prepare, run, save_npz_atomic

    hit = dict(DEFAULT_HIT, start=0.1)
    setup = prepare(SimulationConfig(duration=0.6, perturbations=[hit]))
    return save_npz_atomic(tmp_path_factory.mktemp("real") / "run.npz", run_arrays(setup, run(setup)))


# ------------------------------------------------------------------ helpers

def _panels(img, frames):
    """Split a filmstrip into its (2, frames) panels."""
    ph, pw = img.shape[0] // 2, img.shape[1] // frames
    return [[img[r * ph:(r + 1) * ph, c * pw:(c + 1) * pw].astype(float) for c in range(frames)]
            for r in range(2)]


def _figure_mask(panel, row):
    """Pixels of the figure: bluish in the original (top) row, orange in the perturbed row.
    Background, ground, separators, labels and the pale ghost are all near-neutral."""
    r, b = panel[..., 0], panel[..., 2]
    return (b - r > 12) if row == 0 else (r - b > 40)


def _check_filmstrip(png, frames, times, hit_start):
    img = iio.imread(png)
    pw, ph = render.PANEL_SIZE
    assert img.shape[:2] == (2 * ph, frames * pw)
    assert img.std() > 20                                     # far from blank
    panels = _panels(img, frames)
    masks = [[_figure_mask(panels[r][c], r) for c in range(frames)] for r in range(2)]
    for c in range(frames):
        for r in range(2):
            assert masks[r][c].mean() > 0.01, (r, c)         # every panel shows its figure
        assert _figure_mask(panels[0][c], 1).mean() < 0.002   # nothing orange in the top row
    before = [c for c in range(frames) if times[c] < hit_start]
    after = [c for c in range(frames) if times[c] > hit_start + 0.05]
    assert before and after, times
    # Same camera and pose before the hit: the two silhouettes coincide; after it they differ.
    xor = [np.logical_xor(masks[0][c], masks[1][c]).mean() for c in range(frames)]
    assert max(xor[c] for c in before) < 0.002, xor
    assert max(xor[c] for c in after) > 5 * max(max(xor[c] for c in before), 1e-3), xor
    return xor


# ------------------------------------------------------------------ tests: synthetic

def test_filmstrip_synthetic(synth, tmp_path):
    out = tmp_path / "film.png"
    render_run(synth, out, frames=5)
    scene = Scene(render.load_run(synth))
    times = scene.time[scene.index_at(scene.filmstrip_times(5))]
    assert times[0] < HIT_START < times[1] and times[-1] > HIT_START + 0.3
    _check_filmstrip(out, 5, times, HIT_START)
    assert not list(tmp_path.glob(".film*"))                   # no temporary left behind


def test_filmstrip_draws_force_arrow(synth, tmp_path):
    """A panel while the force acts has red arrow pixels; the same instant without force has none."""
    d = synthetic_run()
    on = np.flatnonzero(np.linalg.norm(d["force_vector"], axis=1) > 0)
    scene = Scene(d)
    k = on[len(on) // 2]
    assert scene.force_on[k]
    tail, tip = scene.arrow(k)
    f = d["force_vector"][k]
    # Points along the force, 1 m per 500 N, tip just outside the bone at the application point.
    assert np.allclose(tip - tail, f / 500.0)
    back = d["force_origin"][k] - tip
    assert np.allclose(np.cross(back, f), 0.0, atol=1e-12) and np.dot(back, f) > 0
    assert 0.035 < np.linalg.norm(back) <= 0.035 + 0.01 + 1e-9

    def red_fraction(arrays):
        # One-frame filmstrip at the hit's peak.
        arrays = {**arrays, "time": arrays["time"]}
        path = _save(tmp_path / f"r{len(list(tmp_path.iterdir()))}.npz", arrays)
        png = tmp_path / f"{path.stem}.png"
        render_run(path, png, frames=1)
        img = iio.imread(png)[..., :3].astype(int)
        return ((img[..., 0] > 180) & (img[..., 1] < 60) & (img[..., 2] < 60)).mean()

    # Keep a single sample of force so the one-frame strip lands on it.
    d1 = dict(d)
    f = np.zeros_like(d["force_vector"])
    f[k] = d["force_vector"][k]
    d1["force_vector"] = f
    d0 = dict(d, force_vector=np.zeros_like(f))
    d0["skeleton_points_unperturbed"] = d0["skeleton_points"]
    assert red_fraction(d1) > 0.0005   # seen three-quarter on, the arrow is foreshortened
    assert red_fraction(d0) == 0.0


def _purple(img):
    """Pixels of the balance assist's arrow (io.palette.COLOR_ASSIST, shaded)."""
    r, g, b = (img[..., i].astype(int) for i in range(3))
    return (g < 90) & (b > 130) & (r > 80) & (b - g > 70)


def test_filmstrip_and_video_draw_the_balance_assist(tmp_path):
    """A run with the assist on (RUN.npz assist_force at assist_point): its purple arrow, F / 500 N
    per m from the pelvis, and its label in the perturbed row of the filmstrip and in the video's
    frames; none in the original row, and none without the assist."""
    d = synthetic_run(duration=0.4)
    T = len(d["time"])
    force = np.zeros((T, 3))
    force[:, 0] = 150.0 * np.sin(np.pi * d["time"] / d["time"][-1])  # a pull toward +x, peak mid-run
    helped = dict(d, assist_force=force, assist_point=d["skeleton_points"][:, 0].copy())
    scene = Scene(helped)
    k = T // 2
    tail, tip = scene.assist_arrow(k)
    np.testing.assert_allclose(tip - tail, force[k] / 500.0)
    np.testing.assert_allclose(tail, d["skeleton_points"][k, 0])
    assert scene.assist_on[k] and not Scene(d).assist_on.any()
    assert scene.assist_label(k) == f"assist {np.linalg.norm(force[k]):.0f} N (not physics)"
    for arrays, name in ((helped, "helped"), (d, "plain")):
        npz = _save(tmp_path / f"{name}.npz", arrays)
        render_run(npz, tmp_path / f"{name}.png", frames=3)
        img = iio.imread(tmp_path / f"{name}.png")[..., :3]
        half = img.shape[0] // 2
        if name == "helped":
            assert _purple(img[half:]).mean() > 2e-4  # the perturbed row shows the arrow
        else:
            assert _purple(img[half:]).sum() == 0
        assert _purple(img[:half]).sum() == 0  # never on the original
        render_run(npz, tmp_path / f"{name}.mp4", progress=False)
        frames = np.stack(list(iio.imiter(tmp_path / f"{name}.mp4", plugin="FFMPEG")))
        seen = _purple(frames[len(frames) // 2]).mean()
        assert seen > 2e-4 if name == "helped" else seen < 1e-5  # (the codec may tint an edge)


def test_video_mp4_and_gif_synthetic(tmp_path):
    arrays = synthetic_run(duration=0.4)
    npz = _save(tmp_path / "run.npz", arrays)
    for ext, fps in ((".mp4", 30.0), (".gif", 25.0)):
        out = tmp_path / f"video{ext}"
        render_run(npz, out, progress=False)
        frames = iio.imread(out, index=None) if ext == ".gif" else np.stack(list(iio.imiter(out, plugin="FFMPEG")))
        expected = int(np.floor(0.4 * fps + 1e-9)) + 1
        assert frames.shape[0] == expected, (ext, frames.shape)
        assert frames.shape[1:3] == (render.VIDEO_SIZE[1], render.VIDEO_SIZE[0])
        assert frames[..., :3].std() > 20
        # The picture changes over time (arms swing, the body leans).
        assert np.abs(frames[0].astype(float) - frames[-1].astype(float)).mean() > 1.0
    meta = iio.immeta(tmp_path / "video.mp4", plugin="FFMPEG")
    assert abs(meta["fps"] - 30.0) < 0.01


def test_ball_is_drawn(tmp_path):
    arrays = synthetic_run(duration=0.5, with_ball=True)
    npz = _save(tmp_path / "run.npz", arrays)
    out = tmp_path / "film.png"
    render_run(npz, out, frames=3)
    img = iio.imread(out)[..., :3].astype(int)
    yellow = (img[..., 0] > 200) & (img[..., 1] > 170) & (img[..., 2] < 90)
    assert yellow.mean() > 1e-4                                 # the yellow ball appears
    # Only in the perturbed (bottom) row.
    assert yellow[: img.shape[0] // 2].sum() == 0


def test_plot_run_synthetic(synth, tmp_path):
    out = tmp_path / "plot.png"
    plot_run(synth, out)
    img = iio.imread(out)[..., :3].astype(float)
    assert img.shape[0] > 400 and img.shape[1] > 600
    assert img.std() > 10
    orange = (img[..., 0] > 200) & (np.abs(img[..., 1] - 127) < 40) & (img[..., 2] < 60)
    assert orange.mean() > 1e-4                                 # the deviation curve is drawn


@pytest.mark.parametrize("drop", ["skeleton_points", "force_vector", "skeleton_edges"])
def test_missing_field_names_it_and_leaves_no_file(tmp_path, drop):
    arrays = synthetic_run(duration=0.3)
    del arrays[drop]
    npz = _save(tmp_path / "bad.npz", arrays)
    for out in (tmp_path / "o.png", tmp_path / "o.mp4", tmp_path / "o.gif"):
        with pytest.raises(RenderError, match=drop):
            render_run(npz, out)
        assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz"]


def test_bad_inputs(tmp_path, synth):
    with pytest.raises(RenderError, match="nope.npz"):
        render_run(tmp_path / "nope.npz", tmp_path / "o.png")
    with pytest.raises(RenderError, match=r"o\.jpg.*\.png"):
        render_run(synth, tmp_path / "o.jpg")
    arrays = synthetic_run(duration=0.3)
    arrays["skeleton_points"] = arrays["skeleton_points"][:, :, :2]
    npz = _save(tmp_path / "shape.npz", arrays)
    with pytest.raises(RenderError, match="skeleton_points"):
        render_run(npz, tmp_path / "o.png")
    arrays = synthetic_run(duration=0.3)
    arrays["skeleton_points"][5, 3, 1] = np.nan
    npz = _save(tmp_path / "nan.npz", arrays)
    with pytest.raises(RenderError, match="skeleton_points.*non-finite"):
        render_run(npz, tmp_path / "o.png")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(RenderError, match="junk.npz"):
        render_run(tmp_path / "junk.npz", tmp_path / "o.png")
    arrays = synthetic_run(duration=0.3)
    del arrays["theta_desired"]
    npz = _save(tmp_path / "noplot.npz", arrays)
    with pytest.raises(RenderError, match="theta_desired"):
        plot_run(npz, tmp_path / "p.png")
    assert not (tmp_path / "o.png").exists() and not (tmp_path / "p.png").exists()
    assert not list(tmp_path.glob(".o.*")) and not list(tmp_path.glob(".p.*"))


def test_cli_plot_and_render(synth, tmp_path, capsys):
    from neuromotor.cli import main

    assert main(["plot", str(synth), "-o", str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").stat().st_size > 10_000
    assert main(["render", str(tmp_path / "missing.npz"), "-o", str(tmp_path / "x.png")]) == 2
    assert "missing.npz" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


# ------------------------------------------------------------------ tests: a real run

@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")   # ffmpeg subprocess after JAX
def test_real_run_filmstrip_video_plot(real_run, tmp_path):
    d = np.load(real_run)
    t = d["time"]
    on = t[np.linalg.norm(d["force_vector"], axis=1) > 0]
    assert on.size and abs(on[0] - 0.1) < 0.02
    png = tmp_path / "film.png"
    render_run(real_run, png, frames=4)
    scene = Scene(render.load_run(real_run))
    times = scene.time[scene.index_at(scene.filmstrip_times(4))]
    _check_filmstrip(png, 4, times, on[0])
    mp4 = tmp_path / "video.mp4"
    render_run(real_run, mp4, progress=False)
    n = sum(1 for _ in iio.imiter(mp4, plugin="FFMPEG"))
    assert n == len(render.video_sample_times(t, 30.0)) == int(np.floor((t[-1] - t[0]) * 30 + 1e-9)) + 1
    plot = tmp_path / "plot.png"
    plot_run(real_run, plot)
    assert iio.imread(plot)[..., :3].std() > 10


# ------------------------------------------------------------------ tests: body shapes and camera

def _horizontal_angle_deg(a, b, up):
    a = a - np.dot(a, up) * up
    b = b - np.dot(b, up) * up
    return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


def _variant_run(name, R, up_axis, **kw):
    d = rotate_run(synthetic_run(with_bodies=True, **kw), R)
    d["up_axis"] = np.asarray(up_axis)
    return d


@pytest.mark.parametrize("name,R,up_axis", _variants(), ids=[v[0] for v in _variants()])
def test_camera_looks_at_the_front_whatever_up_axis_and_heading(name, R, up_axis):
    """The camera's horizontal view direction is 0-50 degrees off the character's facing (a
    front or three-quarter view), for a Y-up run, the same run turned Z-up and turned by a random
    heading; the facing is found from the skeleton (the synthetic figure's toes point along +x
    before the turn) and, when the run stores it, taken from ``facing``."""
    up = np.eye(3)[up_axis]
    true_facing = R @ np.array([1.0, 0.0, 0.0])
    for stored in (False, True):
        d = _variant_run(name, R, up_axis)
        if stored:
            d["facing"] = true_facing + 0.3 * up      # not horizontal: the renderer projects it
        scene = Scene(d)
        assert _horizontal_angle_deg(scene.facing, true_facing, up) < 1.0
        assert abs(scene.facing @ up) < 1e-9
        assert 0.0 <= _horizontal_angle_deg(scene.view, true_facing, up) <= 50.0
        assert 5.0 <= np.degrees(np.arcsin(scene.view @ up)) <= 20.0   # elevated, looking down
        # The camera a renderer actually gets, from the pyvista plotter.
        import pyvista as pv

        pl = pv.Plotter(off_screen=True, window_size=(64, 64))
        try:
            focal = d["skeleton_points"][0, 0]
            set_camera(pl, scene, focal, 1.0)
            eye = np.asarray(pl.camera.position) - np.asarray(pl.camera.focal_point)
            assert 0.0 <= _horizontal_angle_deg(eye, true_facing, up) <= 50.0
            assert np.asarray(pl.camera.up) @ up > 0.9
        finally:
            pl.close()
        # The hit (along +z before the turn, from the character's left) still reads: the camera
        # sees it from the side it comes from, at a good angle (not end-on).
        hit = R @ np.array([0.0, 0.0, 1.0])
        assert scene.view @ hit < 0
        assert abs(_horizontal_angle_deg(scene.view, hit, up) - 90) < 60


def test_camera_rule_for_hits_from_any_side():
    """For any horizontal hit direction, the view stays within 50 degrees of the facing and on
    the side of the facing that sees the hit most side-on."""
    up = np.array([0.0, 0.0, 1.0])
    facing = np.array([np.cos(0.7), np.sin(0.7), 0.0])
    for ang in np.linspace(0, 2 * np.pi, 13)[:-1]:
        hit = np.array([np.cos(ang), np.sin(ang), 0.0])
        v = render.camera_view(facing, up, hit)
        assert _horizontal_angle_deg(v, facing, up) == pytest.approx(render.CAMERA_AZIMUTH_DEG, abs=1e-6)
        other = render.camera_view(facing, up, hit, azimuth_deg=-render.CAMERA_AZIMUTH_DEG)
        vh, oh = v - (v @ up) * up, other - (other @ up) * up
        assert abs(vh @ hit) <= abs(oh @ hit) + 1e-9


def test_rendering_is_independent_of_up_axis_and_heading(tmp_path):
    """The filmstrip of the same motion is the same picture whether the world is Y-up, Z-up or
    turned by any heading: the camera, framing and ground all follow the character."""
    imgs = {}
    for name, R, up_axis in _variants():
        npz = _save(tmp_path / f"{name}.npz", _variant_run(name, R, up_axis, duration=0.7))
        render_run(npz, tmp_path / f"{name}.png", frames=3)
        imgs[name] = iio.imread(tmp_path / f"{name}.png")[..., :3].astype(float)
    ref = imgs["y-up"]
    assert ref.std() > 20
    for name, img in imgs.items():
        assert np.abs(img - ref).mean() < 0.5, name
        assert (np.abs(img - ref).max(axis=2) > 40).mean() < 1e-3, name


@pytest.mark.parametrize("name,R,up_axis", _variants()[:3], ids=[v[0] for v in _variants()[:3]])
def test_frame_shows_the_character_centred_and_sized(tmp_path, name, R, up_axis):
    """A one-panel filmstrip at the hit's peak: not blank, the figure's (non-background) pixels
    centred in the panel and filling a sensible part of it, and the force arrow drawn."""
    npz = _save(tmp_path / "run.npz", _variant_run(name, R, up_axis, duration=0.7))
    out = tmp_path / "one.png"
    render_run(npz, out, frames=1)
    img = iio.imread(out)[..., :3].astype(float)
    ph, pw = render.PANEL_SIZE[1], render.PANEL_SIZE[0]
    assert img.shape[:2] == (2 * ph, pw)
    assert img.std() > 20
    for row in range(2):
        panel = img[row * ph:(row + 1) * ph]
        mask = _figure_mask(panel, row)
        ys, xs = np.nonzero(mask)
        assert 0.03 < mask.mean() < 0.5, (row, mask.mean())
        height = (ys.max() - ys.min()) / ph
        width = (xs.max() - xs.min()) / pw
        assert 0.55 < height < 0.97, height                  # the body fills most of the height
        assert 0.15 < width < 0.97, width
        cx, cy = 0.5 * (xs.max() + xs.min()) / pw, 0.5 * (ys.max() + ys.min()) / ph
        assert abs(cx - 0.5) < 0.15 and abs(cy - 0.5) < 0.15, (cx, cy)
    red = (img[..., 0] > 150) & (img[..., 1] < 60) & (img[..., 2] < 60)
    assert red[ph:].mean() > 5e-4 and red[:ph].sum() == 0


def _world_vertices(d, k, tag=""):
    """World positions of the shape vertices at sample k from the RUN.npz fields alone."""
    b = d["shape_body"]
    R = np.stack([_quat_matrix(q / np.linalg.norm(q)) for q in d["body_quat" + tag][k]])
    return d["body_pos" + tag][k][b] + np.einsum("vij,vj->vi", R[b], d["shape_vertices"])


def _check_drawn_shapes(d):
    scene = Scene(d)
    assert scene.has_shapes
    for which, tag in (("perturbed", ""), ("original", "_unperturbed")):
        for k in (0, len(d["time"]) // 2):
            geom = FigureGeometry(scene).update(k, which)
            mesh = geom.bodies.mesh
            assert mesh.n_cells == len(d["shape_faces"])
            w = _world_vertices(d, k, tag)
            lo, hi = np.asarray(mesh.points).min(axis=0), np.asarray(mesh.points).max(axis=0)
            assert np.allclose(lo, w.min(axis=0), atol=1e-9) and np.allclose(hi, w.max(axis=0), atol=1e-9)
            b = mesh.bounds
            assert np.allclose([b[0], b[2], b[4]], lo) and np.allclose([b[1], b[3], b[5]], hi)
            # The drawn normals point outward: away from the body's COM.
            pos = d["body_pos" + tag][k][geom.bodies.owner]
            normals = np.asarray(mesh.point_data["Normals"])
            assert np.all(np.einsum("ij,ij->i", normals, np.asarray(mesh.points) - pos) > 0)
    return scene


def test_shapes_drawn_from_the_polyhedra_synthetic():
    d = synthetic_run(with_bodies=True)
    scene = _check_drawn_shapes(d)
    # Only the bones without a body (the toes) are drawn as capsules, thin ones.
    assert sorted(map(tuple, scene.capsule_edges)) == sorted(map(tuple, _EDGES[_TOE_EDGES]))
    assert np.all(scene.capsule_radii <= render.DETAIL_RADIUS_M)
    geom = FigureGeometry(scene).update(0, "perturbed")
    assert geom.capsules is not None and len(geom.meshes()) == 3
    # Without skeleton_edge_body the same bones are found: their midpoints lie in no body.
    d2 = dict(d)
    del d2["skeleton_edge_body"]
    assert sorted(map(tuple, Scene(d2).capsule_edges)) == sorted(map(tuple, _EDGES[_TOE_EDGES]))
    # The ground touches the lowest box corner of the whole run.
    lowest = min(_world_vertices(d, k, tag)[:, 1].min() for k in range(len(d["time"]))
                 for tag in ("", "_unperturbed"))
    assert scene.ground == pytest.approx(min(lowest, (d["skeleton_points"][..., 1].min() - 0.015)))


def test_arrow_tip_on_the_body_surface():
    """With body shapes the arrow's tip sits just outside the body at the point of application:
    1 cm beyond the surface where the line back along the force leaves the shapes."""
    d = synthetic_run(with_bodies=True)
    scene = Scene(d)
    k = int(np.argmax(np.linalg.norm(d["force_vector"], axis=1)))
    tail, tip = scene.arrow(k)
    u = d["force_vector"][k] / np.linalg.norm(d["force_vector"][k])
    assert np.allclose(tip - tail, d["force_vector"][k] / 500.0)
    from scipy.spatial import Delaunay

    w = _world_vertices(d, k)
    hulls = [Delaunay(w[d["shape_body"] == b]) for b in np.unique(d["shape_body"])]

    def inside(x):
        return any(h.find_simplex(x[None])[0] >= 0 for h in hulls)

    o = d["force_origin"][k]
    assert inside(o)
    assert not inside(tip) and not inside(tip + 0.0095 * u)
    assert inside(tip + 0.0105 * u)
    assert np.allclose(np.cross(o - tip, u), 0, atol=1e-12) and (o - tip) @ u > 0.05


def test_old_run_without_shapes_draws_capsules(synth):
    scene = Scene(render.load_run(synth))
    assert not scene.has_shapes
    assert len(scene.capsule_edges) == len(_EDGES)
    geom = FigureGeometry(scene).update(0, "perturbed")
    assert geom.bodies is None and geom.capsules is not None


def test_bad_shape_fields(tmp_path):
    d = synthetic_run(duration=0.3, with_bodies=True)
    bad = dict(d)
    del bad["body_quat"]
    with pytest.raises(RenderError, match="body_quat"):
        render_run(_save(tmp_path / "a.npz", bad), tmp_path / "o.png")
    bad = dict(d, shape_faces=d["shape_faces"] + 1000)
    with pytest.raises(RenderError, match="shape_faces"):
        render_run(_save(tmp_path / "b.npz", bad), tmp_path / "o.png")
    bad = dict(d, shape_body=d["shape_body"][:-1])
    with pytest.raises(RenderError, match="shape_body"):
        render_run(_save(tmp_path / "c.npz", bad), tmp_path / "o.png")
    assert not (tmp_path / "o.png").exists()


def test_real_run_shapes_and_facing(real_run):
    """RUN.npz carries the mass model's polyhedra (drawn exactly where the fields put them) and a
    horizontal unit facing that the skeleton agrees with: the feet point along it."""
    d = dict(np.load(real_run))
    for f in ("shape_vertices", "shape_faces", "shape_body", "skeleton_edge_body", "facing"):
        assert f in d, f
    B = d["body_pos"].shape[1]
    assert set(np.unique(d["shape_body"])) <= set(range(B))
    assert d["shape_faces"].min() >= 0 and d["shape_faces"].max() < len(d["shape_vertices"])
    _check_drawn_shapes(d)
    up = np.eye(3)[int(d["up_axis"])]
    facing = d["facing"]
    assert abs(np.linalg.norm(facing) - 1) < 1e-9 and abs(facing @ up) < 1e-9
    estimate = render.facing_from_skeleton(d["skeleton_points_unperturbed"], d["skeleton_edges"], int(d["up_axis"]))
    assert _horizontal_angle_deg(estimate, facing, up) < 30
    # Feet: the two lowest End Sites, pointing from their joint along the facing.
    pts, edges = d["skeleton_points_unperturbed"][0], d["skeleton_edges"]
    leaves = [c for p, c in edges if c not in edges[:, 0]]
    feet = sorted(leaves, key=lambda i: pts[i] @ up)[:2]
    parent = {c: p for p, c in edges}
    for f in feet:
        toe = pts[f] - pts[parent[f]]
        assert _horizontal_angle_deg(toe, facing, up) < 60
    scene = Scene(render.load_run(real_run))
    assert scene.has_shapes
    assert _horizontal_angle_deg(scene.view, facing, up) <= 50
    # Turned Z-up, the stored facing turns with it and the camera follows.
    dz = rotate_run(d, Y_TO_Z)
    dz["up_axis"] = np.asarray(2)
    sz = Scene(dz)
    assert np.allclose(sz.view, Y_TO_Z @ scene.view, atol=1e-9)
