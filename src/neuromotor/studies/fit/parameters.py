"""What a fit may tune: the muscle feedback pair (ks, kd) and the delayed reflex's gains and
delays (:mod:`neuromotor.physics.reflex`), each fitted as its logarithm (positive, and on the
scale on which it matters)."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from neuromotor.config.specs import FIT_PARAMETERS as PARAMETERS
from neuromotor.errors import ConfigError
from neuromotor.physics.control import Gains

UNITS = dict(zip(PARAMETERS, ("1/s^2", "1/s", "1/s^2", "s", "1/s^2", "s")))
DEFAULT = ("ks", "kd")
_REFLEX = {"reflex_gain": ("spinal", "gain"), "reflex_delay": ("spinal", "delay"),
           "long_latency_gain": ("long_latency", "gain"), "long_latency_delay": ("long_latency", "delay")}


def value(gains: Gains, name: str):
    """The current value of parameter ``name`` in ``gains``."""
    if name in ("ks", "kd"):
        return getattr(gains, name)
    path, leaf = _REFLEX[name]
    return getattr(getattr(gains.reflex, path), leaf)


def with_values(gains: Gains, names: tuple[str, ...], values) -> Gains:
    """``gains`` with the named parameters set to ``values`` (traceable: fit, grad, vmap)."""
    for name, v in zip(names, values):
        if name in ("ks", "kd"):
            gains = dataclasses.replace(gains, **{name: jnp.asarray(v, gains.ks.dtype)})  # type: ignore[arg-type]
            continue
        path, leaf = _REFLEX[name]
        rx = gains.reflex
        assert rx is not None  # a reflex parameter names a reflex
        part = dataclasses.replace(getattr(rx, path), **{leaf: jnp.asarray(v, gains.ks.dtype)})
        gains = dataclasses.replace(gains, reflex=dataclasses.replace(rx, **{path: part}))
    return gains


def start(gains: Gains, names: tuple[str, ...], source: str) -> np.ndarray:
    """x0 = log of the starting values (all must be > 0)."""
    vals = np.array([float(value(gains, n)) for n in names])
    for n, v in zip(names, vals):
        if not v > 0:
            where = "gains" if n in ("ks", "kd") else "reflex"
            raise ConfigError(f"{source}: the fit starts from {n} = {v:g} {UNITS[n]} (field '{where}'), which must "
                              f"be > 0 (parameters are fitted as logarithms)")
    return np.log(vals)


def describe(names: tuple[str, ...], x) -> str:
    """``ks=400, kd=20`` for log-parameters x."""
    return ", ".join(f"{n}={float(np.exp(v)):.6g}" for n, v in zip(names, np.asarray(x)))
