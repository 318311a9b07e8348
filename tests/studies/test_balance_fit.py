"""Fitting the postural loop's gains (issue 38): the fit's forward model is the contact rollout
``neuromotor simulate`` runs on the ground (tests/studies/test_differential.py checks that it
gives the single runs), so its Jacobian goes through the contacts, the delayed loop and the
standing feedforward. Here, on the shipped example (configs/fit_balance.toml: the embedded
clip's upright frame on a free root, pushed at the pelvis and at the chest, 1.5 s at h = 1/120 s):
that Jacobian against central differences, and a fit from the config's start (gains 20-33 %
off) that lands on the truth of a noise-free target."""

from __future__ import annotations

import pathlib

import numpy as np

from neuromotor.config.fields import read_toml
from neuromotor.studies import fit as F
from neuromotor.studies.fit.calibration import calibration_from_dict
from neuromotor.studies.fit.evaluate import ResponseEvaluator

CONFIG = pathlib.Path(__file__).resolve().parents[2] / "configs" / "fit_balance.toml"
TRUTH = np.log([1.5, 0.45])  # balance_kp (m g H per rad), balance_kd (m g H s per rad)


def test_the_loops_gains_are_fitted_through_the_contacts():
    cal = calibration_from_dict(read_toml(CONFIG), str(CONFIG), CONFIG.parent)
    assert cal.problem.scene is not None and cal.problem.names == ("balance_kp", "balance_kd")
    np.testing.assert_allclose(cal.x0, np.log([1.2, 0.3]), rtol=1e-12)  # the start is the config's [balance]
    ev = ResponseEvaluator(cal.problem)
    truth = ev(TRUTH).y
    # The shipped target is the truth plus 0.5 mm of noise (experiments/balance_fit.py).
    assert 0.3e-3 < np.sqrt(np.mean((cal.target - truth) ** 2)) < 0.7e-3
    start = ev(cal.x0)
    assert np.max(np.abs(truth)) > 0.03 and np.max(np.abs(start.y - truth)) > 0.01  # metres: the gains matter
    assert np.all(start.diverged < 0)
    # Forward-mode derivatives through the contact rollout against central differences.
    eps = 1e-6
    for i in range(2):
        e = np.zeros(2)
        e[i] = eps
        fd = (ev(cal.x0 + e).y - ev(cal.x0 - e).y) / (2 * eps)
        assert np.linalg.norm(fd - start.jac[:, i]) <= 1e-4 * np.linalg.norm(start.jac[:, i]), i
    res = F.fit(ev, truth, np.ones_like(truth), cal.x0, "optimistix_lm", cal.options, progress=False, strict=True)
    assert res.status == "converged" and res.iterations >= 2, res.message
    np.testing.assert_allclose(res.x, TRUTH, atol=1e-6)
