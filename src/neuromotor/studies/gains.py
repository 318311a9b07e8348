"""The one way gains reach a controller: :func:`gains_for`.

A prepared setup holds template gains (the per-DOF scaling of Section 5.2, built once by
:func:`~neuromotor.physics.control.make_gains`); every run's controller is that template through
:func:`gains_for`:

* ``prepare`` (and so the CLI's ``--ks``/``--kd`` and the ``[gains]``/``[sim]`` tables, which
  set the config's numbers): ``gains_for(template, config.gains, reflex=...)``;
* sweep grids and experiment controllers: ``gains_for(template, setting)`` for each
  :class:`~neuromotor.config.specs.GainSetting` (and a grid's reflex);
* fits: ``gains_for(gains, **{name: value})`` for the fitted parameters, traced.

The fitted parameters are named (:data:`PARAMETERS`), each with its unit in :data:`UNITS`.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

import jax.numpy as jnp

from neuromotor.config.specs import FIT_PARAMETERS as PARAMETERS, PARAMETER_UNITS, GainSetting
from neuromotor.physics.control import Gains, pd_tracking_gains
from neuromotor.physics.reflex import Reflex

# The unit of each named parameter (by name: the order of PARAMETERS does not matter).
UNITS = PARAMETER_UNITS
# Where a named reflex parameter lives in Gains.reflex: (path, leaf).
_REFLEX = MappingProxyType(
    {
        "reflex_gain": ("spinal", "gain"),
        "reflex_delay": ("spinal", "delay"),
        "long_latency_gain": ("long_latency", "gain"),
        "long_latency_delay": ("long_latency", "delay"),
    }
)
# A named balance parameter's leaf of Gains.balance (neuromotor.physics.balance.Balance).
_BALANCE = MappingProxyType({f"balance_{k}": k for k in ("kp", "kd", "hip_kp", "hip_kd", "delay")})
assert set(UNITS) == set(PARAMETERS) == {"ks", "kd", *_REFLEX, *_BALANCE}


def gains_for(template: Gains, setting: GainSetting | None = None, *, reflex: Reflex | None = None, **values) -> Gains:
    """The controller made from ``template``, in this order:

    * ``setting``: its controller (the paper's feedforward + low-gain feedback, ``neuromotor``,
      or the high-gain PD tracker of :func:`~neuromotor.physics.control.pd_tracking_gains`,
      ``pd``) at its stiffness ``ks`` (1/s^2) and damping ``kd`` (1/s);
    * ``reflex``: the delayed reflex to use (None keeps the template's);
    * ``values``: named parameters of :data:`PARAMETERS` set to values (traceable: fit, grad, vmap).

    The per-DOF scaling of the template (Section 5.2) is kept."""
    gains = template
    if setting is not None:
        gains = gains if setting.controller == "neuromotor" else pd_tracking_gains(gains)
        values = {"ks": setting.ks, "kd": setting.kd, **values}
    if reflex is not None:
        gains = dataclasses.replace(gains, reflex=reflex)
    dtype = gains.ks.dtype
    for name, v in values.items():
        if name in ("ks", "kd"):
            gains = dataclasses.replace(gains, **{name: jnp.asarray(v, dtype)})  # type: ignore[arg-type]  # ks or kd
            continue
        if name in _BALANCE:
            if gains.balance is None:
                raise ValueError(f"{name} needs a controller with the postural loop ([balance] on)")
            value = {_BALANCE[name]: jnp.asarray(v, dtype)}
            gains = dataclasses.replace(gains, balance=dataclasses.replace(gains.balance, **value))  # type: ignore[arg-type]  # a gain leaf
            continue
        if name not in _REFLEX:
            raise ValueError(f"unknown gain parameter {name!r}; choose from {list(PARAMETERS)}")
        path, leaf = _REFLEX[name]
        rx = gains.reflex
        if rx is None:
            raise ValueError(f"{name} needs a controller with a reflex ([reflex] table)")
        part = dataclasses.replace(getattr(rx, path), **{leaf: jnp.asarray(v, dtype)})
        gains = dataclasses.replace(gains, reflex=dataclasses.replace(rx, **{path: part}))
    return gains


def gain_value(gains: Gains, name: str):
    """The current value of parameter ``name`` (of :data:`PARAMETERS`) in ``gains``."""
    if name in ("ks", "kd"):
        return getattr(gains, name)
    if name in _BALANCE:
        return getattr(gains.balance, _BALANCE[name])
    path, leaf = _REFLEX[name]
    return getattr(getattr(gains.reflex, path), leaf)


# The named parameters that are delays (s): each read from a history of limited length.
DELAYS = ("reflex_delay", "long_latency_delay", "balance_delay")


def delay_limits(gains: Gains, h: float) -> dict[str, float]:
    """The longest delay (s) each named delay parameter can take in this controller: its
    history holds ``steps`` grid steps, and a longer delay would read the oldest entry (a
    delay the model never ran). Names of controllers ``gains`` lacks are left out."""
    out = {}
    if gains.reflex is not None:
        out["reflex_delay"] = out["long_latency_delay"] = (gains.reflex.steps - 1) * h
    if gains.balance is not None:
        out["balance_delay"] = (gains.balance.steps - 1) * h
    return out
