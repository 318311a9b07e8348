"""The one place a (ks, kd) pair is set on a controller.

Gains reach a run in one way: a :class:`~neuromotor.config.specs.GainSetting` (or a bare pair
in a fit, where ks and kd are traced) applied to the template gains of a prepared setup by
:func:`set_gains` / :func:`apply_gains`. The CLI's ``--ks``/``--kd``, the ``[gains]`` table,
sweep grids, experiment controllers and the fit's parameters all go through here.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from neuromotor.config.specs import GainSetting
from neuromotor.physics.control import Gains, pd_tracking_gains


def set_gains(template: Gains, ks, kd) -> Gains:
    """``template`` with stiffness ``ks`` (1/s^2) and damping ``kd`` (1/s); keeps the per-DOF
    scaling of :mod:`neuromotor.physics.control` (Section 5.2), traceable in ks and kd."""
    return dataclasses.replace(template, ks=jnp.asarray(ks, template.ks.dtype), kd=jnp.asarray(kd, template.kd.dtype))


def apply_gains(template: Gains, setting: GainSetting) -> Gains:
    """The controller of ``setting``: the paper's feedforward + low-gain feedback, or (``pd``)
    the high-gain PD tracker of :func:`~neuromotor.physics.control.pd_tracking_gains`."""
    base = template if setting.controller == "neuromotor" else pd_tracking_gains(template)
    return set_gains(base, setting.ks, setting.kd)
