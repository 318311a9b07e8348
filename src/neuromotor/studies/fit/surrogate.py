"""Smooth response features of a deviation signal (the fit's feature targets) and their exact
counterparts. Every function is pure JAX and differentiable in the gains through the rollout."""

from __future__ import annotations

from typing import Protocol

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.studies import metrics as mx


class Smoothing(Protocol):
    """The smoothing settings the surrogates read: a :class:`Surrogate`, or the fit's
    :class:`~neuromotor.studies.fit.problem.ResponseSpec` (which carries them)."""

    @property
    def beta(self) -> float: ...
    @property
    def width(self) -> float: ...
    @property
    def fraction(self) -> float: ...
    @property
    def floor_deg(self) -> float: ...
    @property
    def accel_beta(self) -> float: ...


def deviation_deg(theta, theta_ref, dofs=None) -> Float[Array, " T"]:
    """:func:`neuromotor.studies.metrics.deviation` (wrapped differences) with a derivative at zero deviation.

    Before the hit the perturbed and unperturbed runs are identical; d sqrt(u) = du / 2 sqrt(u)
    is then 0/0 and would put NaN in the Jacobian. Where u = 0 the derivative is taken as 0
    (the double-``where`` keeps the NaN out of the unselected branch too).
    """
    return _rms_deg(mx.wrap_angle(theta - theta_ref), dofs)


def _rms_deg(diff, dofs=None) -> Float[Array, " T"]:
    """Zero-safe RMS over DOFs of ``diff`` (radians, or rad/s^2), scaled by 180/pi."""
    if dofs is not None:
        diff = diff[:, dofs]
    u = jnp.mean(diff**2, axis=-1)
    pos = u > 0
    return jnp.rad2deg(jnp.where(pos, jnp.sqrt(jnp.where(pos, u, 1.0)), 0.0))


def acceleration_deg(theta_dot, theta_dot_ref, h: float, dofs=None) -> Float[Array, " T"]:
    """Angular acceleration of the deviation, ``a(t) = rms_i d^2/dt^2 (theta_i - theta_ref_i)``
    in deg/s^2 over ``dofs`` (default all), per sample of the step grid.

    The second derivative is the central difference of the simulated joint rates,
    ``(w[k+1] - w[k-1]) / 2h`` with ``w = theta_dot - theta_dot_ref`` (the rates come from the
    body angular velocities, so this is one difference, not the two of a second difference of
    the angles); the first and last samples, which lack a neighbour, are 0. The RMS over DOFs
    matches :func:`deviation_deg` (same zero-safe square root).
    """
    w = theta_dot - theta_dot_ref
    acc = (w[2:] - w[:-2]) / (2.0 * h)
    inner = _rms_deg(acc, dofs)  # a rate, not an angle: no wrapping
    return jnp.pad(inner, (1, 1))


def joint_acceleration_deg(
    model, quat, omega, quat_ref, omega_ref, h: float, rows=None, mask=None
) -> Float[Array, " T"]:
    """The geodesic counterpart of :func:`acceleration_deg`: per sample, the RMS over joints
    (``rows``; None: all) of |d/dt (w_j - w_ref_j)| in deg/s^2 (``mask``: only these child-frame
    axes, as :func:`neuromotor.studies.metrics.selected_deviation_deg`), w_j the joint's relative
    angular velocity in its child's frame (from body quaternions and angular velocities, so it
    does not depend on how the angles are written); central differences, 0 at both ends."""
    w = mx.joint_rates(model, quat, omega) - mx.joint_rates(model, quat_ref, omega_ref)
    acc = (w[2:] - w[:-2]) / (2.0 * h)
    if rows is not None:
        acc = acc[:, jnp.asarray(rows)]
    if mask is not None:
        acc = acc * jnp.asarray(mask)
    return jnp.pad(jnp.rad2deg(mx.safe_sqrt(jnp.mean(jnp.sum(acc**2, axis=-1), axis=-1))), (1, 1))


def soft_max_weighted(signal, beta: float):
    """Smooth peak of a signal: the softmax(beta * signal)-weighted mean of the signal.

    Below the exact maximum by about ``1 / (2 beta)`` near a rounded peak, whatever the
    signal's length (the log-sum-exp :func:`neuromotor.studies.metrics.soft_peak` is low by up to
    ``log(T) / beta``, too much at the smoothing scale an acceleration in deg/s^2 needs).
    """
    w = jax.nn.softmax(beta * signal)
    return jnp.sum(w * signal)


def exact_peak_acceleration(acc) -> float:
    """The non-smooth counterpart of the ``peak_acceleration_deg_s2`` surrogate: max a(t)."""
    return float(np.max(np.asarray(acc)))


def soft_recovery(time, dev, start, threshold, width: float):
    """Smooth time from ``start`` until d(t) falls below ``threshold`` for good.

    A sample counts while d is still above threshold at that sample *or any later one*:
    ``1 - prod_{s >= t} (1 - above(s))`` with a sigmoid ``above`` (a reverse cumulative
    product, summed in log space). Summed over the samples after ``start`` this is the time
    to the last crossing. The surrogate of :mod:`neuromotor.studies.metrics` integrates the time spent
    above threshold instead, which leaves out the rise before the first crossing and any dip
    below threshold before the last one.
    """
    dt = time[1] - time[0]
    gate = jax.nn.sigmoid((time - start) / dt)
    z = (dev - threshold) / (width * threshold)
    log_below = jax.nn.log_sigmoid(-z)  # log(1 - above)
    never_again = jnp.exp(jnp.cumsum(log_below[::-1])[::-1])
    return jnp.sum(gate * (1.0 - never_again)) * dt


def response_features(time, dev, start, spec: Smoothing, acc=None) -> dict:
    """Smooth peak deviation, time to peak, recovery time and overshoot of a deviation signal
    (``spec``: a :class:`Surrogate` or a :class:`~neuromotor.studies.fit.problem.ResponseSpec`),
    and (given the acceleration signal ``acc`` of :func:`acceleration_deg`) its peak angular
    acceleration.

    Exact counterparts: :func:`neuromotor.studies.metrics.recovery_metrics` (time to peak there is
    absolute; here it is measured from ``start``) and :func:`exact_peak_acceleration`.
    """
    peak = mx.soft_peak(dev, spec.beta)
    t_peak = mx.soft_time_of_peak(time, dev, spec.beta)
    thr = jnp.maximum(spec.fraction * peak, spec.floor_deg)
    rec = soft_recovery(time, dev, start, thr, spec.width)
    # First return below threshold after the peak: the running product of "still above"
    # indicators is ~1 until the first drop and ~0 after, so its integral is the time to it.
    dt = time[1] - time[0]
    after_peak = jax.nn.sigmoid((time - t_peak) / dt)
    still = jnp.cumprod(1.0 - after_peak * (1.0 - jax.nn.sigmoid((dev - thr) / (spec.width * thr))))
    t_return = t_peak + jnp.sum(still * after_peak) * dt
    overshoot = mx.soft_overshoot(time, dev, t_return, spec.beta)
    out = {
        "peak_deviation_deg": peak,
        "time_to_peak_s": t_peak - start,
        "recovery_time_s": rec,
        "overshoot_deg": overshoot,
    }
    if acc is not None:
        out["peak_acceleration_deg_s2"] = soft_max_weighted(acc, spec.accel_beta)
    return out
