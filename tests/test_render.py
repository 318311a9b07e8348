"""Rendering: filmstrip PNG, MP4/GIF video and plots, on a synthetic run and one short real run."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from neuromotor import render
from neuromotor.render import RenderError, plot_run, render_run

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


def synthetic_run(duration=1.0, h=1 / 120, magnitude=300.0, with_ball=False, shift=0.0) -> dict:
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
    return d


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
    from neuromotor.simulate import prepare, run, run_arrays, save_npz_atomic

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
    scene = render._Scene(render.load_run(synth))
    times = scene.time[scene.index_at(scene.filmstrip_times(5))]
    assert times[0] < HIT_START < times[1] and times[-1] > HIT_START + 0.3
    _check_filmstrip(out, 5, times, HIT_START)
    assert not list(tmp_path.glob(".film-*"))                  # no temporary left behind


def test_filmstrip_draws_force_arrow(synth, tmp_path):
    """A panel while the force acts has red arrow pixels; the same instant without force has none."""
    d = synthetic_run()
    on = np.flatnonzero(np.linalg.norm(d["force_vector"], axis=1) > 0)
    scene = render._Scene(d)
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
    assert red_fraction(d1) > 0.001
    assert red_fraction(d0) == 0.0


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
    assert not list(tmp_path.glob(".o-*")) and not list(tmp_path.glob(".p-*"))


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
    scene = render._Scene(render.load_run(real_run))
    times = scene.time[scene.index_at(scene.filmstrip_times(4))]
    _check_filmstrip(png, 4, times, on[0])
    mp4 = tmp_path / "video.mp4"
    render_run(real_run, mp4, progress=False)
    n = sum(1 for _ in iio.imiter(mp4, plugin="FFMPEG"))
    assert n == len(render.video_sample_times(t, 30.0)) == int(np.floor((t[-1] - t[0]) * 30 + 1e-9)) + 1
    plot = tmp_path / "plot.png"
    plot_run(real_run, plot)
    assert iio.imread(plot)[..., :3].std() > 10
