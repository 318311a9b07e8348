"""What a fit may tune: the muscle feedback pair (ks, kd) and the delayed reflex's gains and
delays (:mod:`neuromotor.physics.reflex`), each fitted as its logarithm (positive, and on the
scale on which it matters). They reach the controller through
:func:`neuromotor.studies.gains.gains_for`, which also names them (``PARAMETERS``, ``UNITS``)."""

from __future__ import annotations

import numpy as np

from neuromotor.errors import ConfigError
from neuromotor.physics.control import Gains
from neuromotor.studies.gains import PARAMETERS, UNITS, delay_limits, gain_value  # noqa: F401  (re-exported)

DEFAULT = ("ks", "kd")


def start(gains: Gains, names: tuple[str, ...], source: str) -> np.ndarray:
    """x0 = log of the starting values (all must be > 0)."""
    vals = np.array([float(gain_value(gains, n)) for n in names])
    for n, v in zip(names, vals):
        if not v > 0:
            where = "gains" if n in ("ks", "kd") else "reflex"
            raise ConfigError(
                f"{source}: the fit starts from {n} = {v:g} {UNITS[n]} (field '{where}'), which must "
                f"be > 0 (parameters are fitted as logarithms)"
            )
    return np.log(vals)


def describe(names: tuple[str, ...], x) -> str:
    """``ks=400, kd=20`` for log-parameters x."""
    return ", ".join(f"{n}={float(np.exp(v)):.6g}" for n, v in zip(names, np.asarray(x)))


def beyond_history(gains: Gains, h: float, values: dict) -> str | None:
    """Why ``values`` (name -> value) hold a delay the rollout cannot run, or None: a delay
    past its history's length reads the oldest entry, so the model runs a shorter one."""
    limits = delay_limits(gains, h)
    for name, v in values.items():
        if name in limits and float(v) > limits[name] * (1.0 + 1e-9):
            owner = "balance" if name == "balance_delay" else "reflex"
            return (
                f"{name} = {float(v):.4g} s is beyond the {limits[name]:.4g} s of delay history the "
                f"rollout keeps (it would run {limits[name]:.4g} s): raise [{owner}] max_delay"
            )
    return None
