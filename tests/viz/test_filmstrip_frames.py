"""Filmstrip frames around the hit (hit, peak, recovery), the force label's magnitude, and a
ball drawn only with the perturbed figure (issue 16, item 7)."""

import json

import imageio.v3 as iio
import numpy as np
import pytest

from neuromotor.viz import render
from neuromotor.viz.scene import Scene
from neuromotor.viz.render import render_run

from test_render import HIT_DURATION, HIT_START, _save, synthetic_run


def _scene(arrays, tmp_path, name="run.npz"):
    return Scene(render.load_run(_save(tmp_path / name, arrays)))


def _yellow(img):
    img = img[..., :3].astype(int)
    return (img[..., 0] > 200) & (img[..., 1] > 170) & (img[..., 2] < 90)


def test_force_label_is_the_configured_magnitude(tmp_path):
    arrays = synthetic_run(duration=0.8, magnitude=400.0)
    scene = _scene(arrays, tmp_path)
    k = int(np.flatnonzero(scene.force_on)[0])          # early in the half-sine
    assert scene.fmag[k] < 350.0                         # the sampled force there is lower
    assert scene.force_label(k) == "400 N"               # largest sample of the hit
    arrays["provenance_json"] = np.asarray(json.dumps({"perturbations": [
        {"kind": "force", "magnitude": 412.0, "start": HIT_START, "duration": HIT_DURATION}]}))
    scene = _scene(arrays, tmp_path, "prov.npz")
    assert scene.force_label(k) == "412 N"               # the configured value, exactly
    h = float(scene.time[1] - scene.time[0])
    arrays["provenance_json"] = np.asarray(json.dumps({"perturbations": [  # centred on start: k precedes it
        {"kind": "impulse", "magnitude": 20.0, "start": float(scene.time[k]) + 0.4 * h, "duration": 0.0}]}))
    assert _scene(arrays, tmp_path, "impulse.npz").force_label(k) == "20 N s"  # as configured, not magnitude / h


def test_strip_shows_hit_peak_and_recovery(tmp_path):
    arrays = synthetic_run(duration=1.5)
    # A joint-angle peak (metrics) later than the skeleton's point-wise peak, and a long recovery.
    arrays["metrics_json"] = np.asarray(json.dumps({"time_of_peak_s": 0.9, "recovery_time_s": 0.95}))
    scene = _scene(arrays, tmp_path)
    for n in (4, 6, 8):
        times = scene.filmstrip_times(n)
        assert len(times) == n and np.all(np.diff(times) > 0)
        k_hit = int(np.argmax(scene.fmag))
        assert np.any(np.isclose(times, scene.time[k_hit]))                 # the hit itself
        assert times[0] < HIT_START                                          # before it
        assert np.any(np.isclose(times, 0.9))                                # the peak
        assert times[-1] >= HIT_START + 0.95 - 1e-9                          # the recovery
    assert list(scene.filmstrip_times(3)) == pytest.approx([scene.time[k_hit], 0.9, HIT_START + 0.95], abs=0.02)


def _ball_run(duration=0.8):
    """The synthetic ball run, hitting through a contact force instead of an applied one."""
    arrays = synthetic_run(duration=duration, magnitude=0.0, with_ball=True)
    t = arrays["time"]
    contact = np.zeros((len(t), 2, 3))
    on = (t >= HIT_START) & (t < HIT_START + 0.03)
    contact[on, 0, 2] = -800.0                           # on the ball, a short sharp impact
    arrays["contact_force"] = contact
    return arrays


def test_ball_impact_is_in_the_strip(tmp_path):
    arrays = _ball_run()
    scene = _scene(arrays, tmp_path)
    assert scene.hit_window() is not None and not scene.force_on.any()
    times = scene.filmstrip_times(6)
    assert np.any(np.abs(times - HIT_START) < 0.031)                        # the impact panel
    out = tmp_path / "film.png"
    render_run(_save(tmp_path / "ball.npz", arrays), out, frames=6)
    yellow = _yellow(iio.imread(out))
    assert yellow[yellow.shape[0] // 2:].sum() > 50 and yellow[: yellow.shape[0] // 2].sum() == 0


def test_video_ball_only_on_the_perturbed_side(tmp_path):
    arrays = _ball_run(duration=0.6)
    # The ball comes in from the screen's left, where the original figure stands in the video.
    right = _scene(arrays, tmp_path).right
    t = arrays["time"]
    chest = arrays["skeleton_points"][:, 2]
    s = np.clip(t / HIT_START, 0.0, 1.0)[:, None]
    arrays["ball_pos"] = chest - (1.0 - s) * 2.5 * right + 0.2 * right
    npz = _save(tmp_path / "ball.npz", arrays)
    gif = tmp_path / "video.gif"
    render_run(npz, gif, progress=False)
    frames = iio.imread(gif, index=None)
    W = frames.shape[2]
    ys = [_yellow(f) for f in frames]
    assert max(y[:, : W // 2].sum() for y in ys) == 0                       # never with the original
    assert max(y[:, W // 2:].sum() for y in ys) > 20                          # seen with the perturbed


def test_mp4_after_jax_prints_no_fork_warning(tmp_path):
    """imageio-ffmpeg starts ffmpeg with subprocess (fork + exec); after JAX has started its
    threads that used to print JAX's os.fork() RuntimeWarning (issue 16, item 8)."""
    import warnings

    import jax.numpy as jnp

    (jnp.ones(3) + 1.0).block_until_ready()  # JAX's runtime and threads are up
    npz = _save(tmp_path / "run.npz", synthetic_run(duration=0.3))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        render_run(npz, tmp_path / "video.mp4", progress=False)
    assert (tmp_path / "video.mp4").stat().st_size > 0
    assert not [w for w in caught if "os.fork" in str(w.message)]
