"""Gain calibration: the single (ks, kd) whose simulated reaction to a hit matches a target.

Parameters (:mod:`.parameters`). By default ``x = (log ks, log kd)``: the gains stay positive and
both are fitted on the scale on which they matter (a factor, not an increment). ``[fit]
parameters`` picks any subset of ks, kd and the delayed reflex's gains and delays
(``reflex_gain``, ``reflex_delay``, ``long_latency_gain``, ``long_latency_delay``; see
:mod:`neuromotor.physics.reflex`), each fitted as its logarithm; the others stay at the config's
values.

Residuals (:mod:`.problem`, :mod:`.surrogate`). Given C perturbation cases, simulated jointly by
one ``vmap`` over the case axis of a :class:`~neuromotor.physics.perturbation.ForcePulses`, the
model output y(x) stacks over cases either the simulated trajectory inside the fit window (joint
angles of all or named DOFs, or body COM positions), or smooth response features of the
deviation from the unperturbed twin (peak deviation, time to peak, recovery time, overshoot,
peak angular acceleration), the unperturbed run being one extra member of the batch. The
residual is ``r(x) = w * (y(x) - y_target)`` with per-entry weights w (a per-DOF weight, or
1/sd for a feature). **What is minimized**: ``L(x) = 1/2 ||r(x)||^2``, through the whole rollout.

Derivatives (:mod:`.evaluate`). ``J = dr/dx`` by ``jax.jacfwd`` (two tangents through the scan),
or in reverse mode (``jacobian="reverse"``: one recorded forward pass, then one backward pass
per residual, a few at a time), which pays off when residuals are few or parameters many.

Solvers (:mod:`.solvers`, by name in :data:`FIT_SOLVERS`): optimistix Levenberg-Marquardt,
Gauss-Newton with an Armijo line search (:class:`GaussNewtonLineSearch`) and BFGS, jaxopt
Levenberg-Marquardt and L-BFGS. All see the same residual: :class:`ResponseEvaluator` compiles
``x -> (y, dy/dx)`` once and :func:`residual_function` (:mod:`.bridge`) exposes it as a JAX
function with a custom JVP through ``jax.pure_callback``, so switching solver costs no compile
and every solver is stepped one iteration at a time from Python (progress, divergence checks).
The pure-JAX path (:meth:`FitProblem.residuals`, :func:`loss`) stays for ``jit``/``grad``/``vmap``.

After the fit (:mod:`.driver`, :mod:`.covariance`, :class:`FitResult`): the Gauss-Newton
covariance ``s^2 (J^T J)^-1`` of the log-parameters with ``s^2 = ||r||^2 / (m - p)``, standard
errors (also of the parameters themselves by the delta method), which parameters the target
identifies (:func:`.result.identifiability`: a finite standard error of the log below 0.5; a
delay cannot be told from a gain by one peak value), residual, counts, wall time, and a status:
``converged``, ``converged (loss flat)`` (the step limit was reached with the loss flat:
relative change below ``LOSS_FLAT_RTOL`` in each of the last ``LOSS_FLAT_ITERATIONS``
iterations; counts as converged), ``max_steps``, ``diverged``, ``nonfinite`` (the last finite
iterate is returned) or ``out_of_range`` (a fitted delay is longer than the delay history the
fit simulated, so the model ran a shorter one: raise ``max_delay``). A fit never returns NaN
gains; with ``strict=True`` anything but the two converged statuses raises :class:`FitError`.

Config files (:mod:`.calibration`): the ``[fit]`` table is parsed by
:func:`neuromotor.config.fit_spec`; synthetic targets are in :mod:`.synthetic`, the plot in
:mod:`neuromotor.viz.fit_plots`.
"""

from neuromotor.config.specs import FEATURE_NAMES, FIT_SOLVERS, TARGET_KINDS as KINDS, SolverOptions
from neuromotor.studies.fit.bridge import residual_function
from neuromotor.studies.fit.calibration import (
    Calibration,
    calibrate,
    calibration_from_dict,
    calibration_from_spec,
    load_calibration,
    trajectory_calibration,
)
from neuromotor.studies.fit.covariance import gauss_newton_covariance
from neuromotor.studies.fit.driver import fit
from neuromotor.studies.fit.evaluate import REVERSE_BATCH, Evaluation, ResponseEvaluator, compiled_response
from neuromotor.studies.fit.parameters import PARAMETERS
from neuromotor.studies.fit.problem import FitProblem, ResponseSpec, loss, make_problem
from neuromotor.studies.fit.result import (
    CONVERGED_STATUSES,
    IDENTIFIABLE_SE_LOG,
    LOSS_FLAT_ITERATIONS,
    LOSS_FLAT_RTOL,
    FitError,
    FitResult,
    identifiability,
    loss_is_flat,
)
from neuromotor.studies.fit.solvers import GaussNewtonLineSearch, run_solver
from neuromotor.studies.fit.surrogate import (
    acceleration_deg,
    deviation_deg,
    exact_peak_acceleration,
    response_features,
    soft_max_weighted,
    soft_recovery,
)
from neuromotor.studies.fit.synthetic import record_trial, synthetic_target, truth_recovery, write_synthetic_target

__all__ = [
    "CONVERGED_STATUSES",
    "Calibration",
    "Evaluation",
    "FEATURE_NAMES",
    "FitError",
    "FitProblem",
    "FitResult",
    "IDENTIFIABLE_SE_LOG",
    "PARAMETERS",
    "identifiability",
    "GaussNewtonLineSearch",
    "KINDS",
    "LOSS_FLAT_ITERATIONS",
    "LOSS_FLAT_RTOL",
    "REVERSE_BATCH",
    "ResponseEvaluator",
    "ResponseSpec",
    "FIT_SOLVERS",
    "SolverOptions",
    "acceleration_deg",
    "calibrate",
    "calibration_from_dict",
    "calibration_from_spec",
    "compiled_response",
    "deviation_deg",
    "exact_peak_acceleration",
    "fit",
    "gauss_newton_covariance",
    "load_calibration",
    "loss",
    "loss_is_flat",
    "make_problem",
    "record_trial",
    "residual_function",
    "response_features",
    "run_solver",
    "soft_max_weighted",
    "soft_recovery",
    "synthetic_target",
    "trajectory_calibration",
    "truth_recovery",
    "write_synthetic_target",
]
