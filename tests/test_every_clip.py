"""Every shipped clip end to end at the default gains: the unperturbed replay follows the
capture, and a 300 N push on the chest (a segment keyword, so the same config serves every rig)
is recovered from."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import ALL_CLIPS
from neuromotor.config import SimulationConfig
from neuromotor.simulate import prepare, run

PUSH = dict(kind="force", body="chest", point=None, direction=[1.0, 0.0, 0.0], magnitude=300.0,
            start=1.0, duration=0.1, shape="half_sine")
# (RMS, worst DOF's RMS) bounds of the unperturbed replay over 3 s, degrees. The Bandai-Namco kick
# stays above the 1 deg / 3 deg target at h = 1/120 s (its Spine sits within 3-10 deg of gimbal
# lock for the whole clip and the kicks are fast); docs/body-model.md gives the figures, and at
# h = 1/240 s it reaches 1.06 deg. Its bound here guards against regressions.
BOUNDS = {"bandai_kick_22joint_6ch": (2.2, 5.5)}


@pytest.fixture(scope="module", params=sorted(ALL_CLIPS), ids=str)
def result(request):
    cfg = SimulationConfig(clip=str(ALL_CLIPS[request.param]), duration=3.0, perturbations=[dict(PUSH)])
    setup = prepare(cfg)
    return request.param, setup, run(setup)


def test_unperturbed_replay_follows_the_capture(result):
    name, setup, res = result
    theta = np.asarray(res.unperturbed.theta)
    err = np.degrees(np.angle(np.exp(1j * (theta - np.asarray(setup.ref.theta)[: len(theta)]))))
    rms, worst = float(np.sqrt(np.mean(err**2))), float(np.sqrt(np.mean(err**2, axis=0)).max())
    bound_rms, bound_dof = BOUNDS.get(name, (1.0, 3.0))
    assert rms < bound_rms and worst < bound_dof, (name, rms, worst)
    np.testing.assert_allclose(res.metrics["unperturbed_rms_error_deg"], rms, rtol=1e-6)
    assert res.metrics["max_kkt_residual"] < 1e-9 and res.metrics["max_constraint_violation"] < 1e-8


def test_chest_push_deflects_and_recovers(result):
    name, setup, res = result
    m = res.metrics
    assert not m["diverged"]
    assert m["peak_deviation_deg"] > 0.5  # the push is felt...
    assert 1.0 < m["time_of_peak_s"] < 2.0
    if name in BOUNDS:  # ...and dies down (the kick's own drift keeps it above the 0.5 deg line)
        assert m["final_error_deg"] < 0.35 * m["peak_deviation_deg"]
    else:  # ...and is recovered from within the window
        assert np.isfinite(m["recovery_time_s"]) and m["final_error_deg"] < 0.5
