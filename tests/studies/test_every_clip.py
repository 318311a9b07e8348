"""Every shipped clip end to end at the default gains: the unperturbed replay follows the
capture, and a 300 N push on the chest (a segment keyword, so the same config serves every rig)
is recovered from."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ALL_CLIPS, CLIPS
from neuromotor.studies import metrics as mx
from neuromotor.config import SimulationConfig
from neuromotor.studies.simulate import prepare, run, step_warnings

PUSH = dict(kind="force", body="chest", point=None, direction=[1.0, 0.0, 0.0], magnitude=300.0,
            start=1.0, duration=0.1, shape="half_sine")
# The Bandai-Namco kick: its push decays to a tenth of its peak, and the next kick (at 2.8 s)
# excites the difference again.
KICK = {"bandai_kick_22joint_6ch"}


# MocapBank and walk replay and recover in tests/physics/test_forward_dynamics.py (whole clips, the
# default hit) and the chest keyword resolves on them in tests/model/test_massmodel.py: here the clips
# that nothing else simulates, to keep the suite's time.
OTHERS = sorted(name for name, path in ALL_CLIPS.items() if path not in CLIPS.values())


@pytest.fixture(scope="module", params=OTHERS, ids=str)
def result(request):
    cfg = SimulationConfig(clip=str(ALL_CLIPS[request.param]), duration=3.0, perturbations=[dict(PUSH)])
    setup = prepare(cfg)
    return request.param, setup, run(setup)


def test_fast_spinning_root_is_warned_about_only_with_the_continuous_feedforward(result):
    """The kick's root spins at 11 rad/s: at h = 1/120 s the discrete feedforward replays it
    exactly (no warning); Eq. 3's would drift by degrees, and prepare() would warn."""
    name, setup, _ = result
    assert not setup.warnings or not any("rad per step" in w for w in setup.warnings)
    assert not step_warnings(setup.ref, setup.options.h)
    continuous = step_warnings(setup.ref, 1.0 / 120.0, "continuous")
    assert bool(continuous) == (name in KICK)
    if continuous:
        assert "rad per step" in continuous[0] and "sim.h <=" in continuous[0]


def test_unperturbed_replay_is_the_capture(result):
    """Every joint at every sample within 0.01 deg of the capture (geodesic angle of its local
    rotation), at the default step; the replay error the metrics report agrees, and so do the
    Euler angles."""
    name, setup, res = result
    local = mx.joint_quats(setup.model, res.unperturbed.states.quat)
    err = np.degrees(np.asarray(mx.geodesic_angle(local, setup.ref.rel_quat[: local.shape[0]])))
    assert err.max() < 0.01, (name, err.max())
    np.testing.assert_allclose(res.metrics["unperturbed_rms_error_deg"], np.sqrt(np.mean(err**2)), rtol=1e-6,
                               atol=1e-12)
    theta = np.asarray(res.unperturbed.theta)
    euler = np.degrees(np.angle(np.exp(1j * (theta - np.asarray(setup.ref.theta)[: len(theta)]))))
    assert np.abs(euler).max() < 0.01
    assert res.metrics["max_kkt_residual"] < 1e-9 and res.metrics["max_constraint_violation"] < 1e-8


def test_chest_push_deflects_and_recovers(result):
    name, setup, res = result
    m = res.metrics
    assert not m["diverged"]
    assert m["peak_deviation_deg"] > 0.5  # the push is felt...
    assert 1.0 < m["time_of_peak_s"] < 2.0
    dev = np.asarray(mx.joint_deviation(setup.model, res.perturbed.states.quat, res.unperturbed.states.quat))
    t = np.asarray(res.perturbed.time)
    # 1.8 s after the push the deviation is below a quarter of its peak (issue 34's criterion).
    assert dev[np.argmin(np.abs(t - (PUSH["start"] + 1.8)))] < 0.25 * dev.max()
    if name in KICK:  # ...and dies down before the next kick
        assert dev[(t > m["time_of_peak_s"]) & (t < 2.7)].min() < 0.2 * m["peak_deviation_deg"]
        assert m["final_error_deg"] < 0.35 * m["peak_deviation_deg"]
    else:  # ...and is recovered from within the window
        assert np.isfinite(m["recovery_time_s"]) and m["final_error_deg"] < 0.5 * np.sqrt(3)
