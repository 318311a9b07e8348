"""What a fit reports, and the errors a failed fit raises."""

from __future__ import annotations

import dataclasses

import numpy as np

from neuromotor.io.tables import json_safe as _json_safe


class FitError(RuntimeError):
    (
        """The fit failed (no convergence, diverged rollout, non-finite iterate); carries the result.
    Not a user error: ``neuromotor fit`` reports it with its own exit status (3)."""
        ""
    )

    def __init__(self, message: str, result: FitResult | None = None):
        super().__init__(message)
        self.result = result


LOSS_FLAT_RTOL = 1e-8  # relative change of the loss per iteration that counts as none


LOSS_FLAT_ITERATIONS = 3  # ... over this many consecutive iterations


CONVERGED_STATUSES = ("converged", "converged (loss flat)")


def loss_is_flat(losses, rtol: float = LOSS_FLAT_RTOL, n: int = LOSS_FLAT_ITERATIONS) -> bool:
    """True when each of the last ``n`` changes of the loss (a sequence over iterations) is
    below ``rtol`` relative to the loss before it: the fit has converged in its objective even
    if the solver's step-size test has not fired (the gains then move by round-off only)."""
    vals = [float(v) for v in losses if v is not None]
    if len(vals) < n + 1:
        return False
    tail = np.asarray(vals[-(n + 1) :])
    if not np.all(np.isfinite(tail)):
        return False
    return bool(np.all(np.abs(np.diff(tail)) <= rtol * np.maximum(np.abs(tail[:-1]), 1e-300)))


IDENTIFIABLE_SE_LOG = 0.5  # a log-parameter with a larger standard error (a factor 1.65) is not identifiable


def identifiability(names, se_log, cov) -> tuple[dict, str]:
    """Which fitted parameters the target determines: standard error of the log-parameter at
    most :data:`IDENTIFIABLE_SE_LOG`. A parameter the residuals do not see, or one that others
    can stand in for (J^T J singular: e.g. two parameters from one peak value), has an infinite
    standard error."""
    ok = {n: bool(np.isfinite(s) and s <= IDENTIFIABLE_SE_LOG) for n, s in zip(names, se_log)}
    bad = [n for n in names if not ok[n]]
    if not bad:
        return ok, "every fitted parameter is identifiable from this target"
    why = (
        "the target does not determine them (J^T J is singular: fewer independent residuals than "
        "parameters, or parameters that trade off exactly)"
        if not np.all(np.isfinite(cov))
        else f"standard error of the log above {IDENTIFIABLE_SE_LOG} (the value is uncertain by more than a factor "
        f"{np.exp(IDENTIFIABLE_SE_LOG):.2f})"
    )
    return ok, f"not identifiable from this target: {', '.join(bad)}; {why}"


@dataclasses.dataclass
class FitResult:
    """Everything the calibration reports (``to_json`` gives the JSON contract)."""

    solver: str
    status: str  # converged | converged (loss flat) | max_steps | diverged | nonfinite | out_of_range
    message: str
    ks: float
    kd: float
    ks0: float
    kd0: float
    log_params: list[float]
    covariance_log: list[list[float]]  # Gauss-Newton s^2 (J^T J)^-1 of the log-parameters (order: parameters)
    se_log: list[float]
    se_ks: float
    se_kd: float
    correlation: float
    s2: float
    residual_norm: float
    residual_rms: float
    loss: float
    n_residuals: int
    iterations: int
    evaluations: int
    wall_time_s: float
    jacobian: str
    diverged_evaluations: int
    history: list[dict]
    parameters: list[str] = dataclasses.field(default_factory=lambda: ["ks", "kd"])  # fitted, in x's order
    values: dict = dataclasses.field(default_factory=dict)  # fitted value of each parameter
    start_values: dict = dataclasses.field(default_factory=dict)
    standard_errors: dict = dataclasses.field(default_factory=dict)  # absolute, by the delta method
    identifiable: dict = dataclasses.field(default_factory=dict)  # name -> bool
    identifiability: str = ""  # what the target does not determine, in words

    @property
    def converged(self) -> bool:
        return self.status in CONVERGED_STATUSES

    @property
    def x(self) -> np.ndarray:
        return np.asarray(self.log_params)

    def to_json(self) -> dict:
        return _json_safe(dataclasses.asdict(self))
