"""Recovery metrics of a perturbed rollout against its unperturbed twin.

The deviation signal is ``d(t) = sqrt(mean_i wrap(theta_i - theta_unperturbed_i)^2)`` in
degrees over the simulated DOFs (or a chosen subset), where ``wrap`` gives the shortest signed
angle (a joint that turns by 356 degrees has moved by -4 degrees, not 356). From it:

* peak deviation (deg) and its time (s);
* recovery time (s): from the perturbation's start until d(t) falls below
  ``max(recovery_fraction * peak, recovery_floor_deg)`` and stays below to the end (NaN if it
  never does);
* final error (deg): d at the last sample;
* overshoot (deg): the largest deviation after the first time d drops below the threshold.

Each has a smooth surrogate for gradient-based fitting: a log-sum-exp peak, a softmax-weighted
peak time, and a sigmoid-integrated recovery time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

RECOVERY_FRACTION = 0.2
RECOVERY_FLOOR_DEG = 0.5


def wrap_angle(a):
    """The angle equal to ``a`` modulo 2 pi in [-pi, pi] (the shortest signed difference when
    ``a`` is a difference of angles). ``atan2(sin a, cos a)``: smooth, with derivative 1
    everywhere, so it can sit inside ``jacfwd``/``grad`` (fitting)."""
    return jnp.arctan2(jnp.sin(a), jnp.cos(a))


def wrap_angle_np(a) -> np.ndarray:
    """:func:`wrap_angle` in NumPy (no device round trip)."""
    a = np.asarray(a, dtype=np.float64)
    return np.arctan2(np.sin(a), np.cos(a))


def continuous_angles(theta, reference=None) -> np.ndarray:
    """(T, n) angles made continuous in time (``np.unwrap`` along axis 0), each column then
    shifted by a whole number of turns so that its first sample is the branch nearest
    ``reference[0]`` (e.g. the mocap's angles; default: the wrapped first sample)."""
    theta = np.unwrap(np.asarray(theta, dtype=np.float64), axis=0)
    if theta.shape[0] == 0:
        return theta
    first = theta[0]
    target = wrap_angle_np(first) if reference is None else np.asarray(reference, dtype=np.float64)[0]
    turns = np.round((first - target) / (2 * np.pi))
    return theta - 2 * np.pi * turns


def deviation(theta, theta_ref, dofs=None) -> Float[Array, " T"]:
    """RMS over DOFs of the wrapped (shortest) angle difference, degrees, per time sample."""
    diff = wrap_angle(theta - theta_ref)
    if dofs is not None:
        diff = diff[:, jnp.asarray(dofs)]
    return jnp.rad2deg(jnp.sqrt(jnp.mean(diff**2, axis=-1)))


def rms_error_deg(theta, theta_ref) -> float:
    """RMS of the wrapped angle differences over all samples and DOFs, degrees."""
    diff = wrap_angle_np(np.asarray(theta) - np.asarray(theta_ref))
    return float(np.rad2deg(np.sqrt(np.mean(diff ** 2))))


def recovery_metrics(time, dev, start: float, fraction: float = RECOVERY_FRACTION,
                     floor_deg: float = RECOVERY_FLOOR_DEG) -> dict[str, float]:
    """Exact (non-smooth) metrics of a deviation signal, as plain floats."""
    time, dev = np.asarray(time), np.asarray(dev)
    ipk = int(np.argmax(dev))
    peak = float(dev[ipk])
    thr = max(fraction * peak, floor_deg)
    after = time >= start
    above = (dev > thr) & after
    if peak <= floor_deg:
        rec, first_below = 0.0, ipk
    elif above[-1]:
        rec, first_below = float("nan"), len(dev)
    else:
        last_above = int(np.nonzero(above)[0][-1]) if above.any() else ipk
        rec = float(time[last_above + 1] - start)
        below = np.nonzero((dev <= thr) & (time > time[ipk]))[0]
        first_below = int(below[0]) if below.size else len(dev)
    overshoot = float(dev[first_below:].max()) if first_below < len(dev) else 0.0
    return {
        "peak_deviation_deg": peak,
        "time_of_peak_s": float(time[ipk]),
        "recovery_time_s": rec,
        "final_error_deg": float(dev[-1]),
        "overshoot_deg": overshoot,
        "recovery_threshold_deg": thr,
    }


def soft_peak(dev, beta: float = 5.0):
    """Smooth max: (1/beta) log sum exp(beta d) - (1/beta) log T (exact as beta -> inf)."""
    return (jax.nn.logsumexp(beta * dev) - jnp.log(dev.shape[0])) / beta


def soft_time_of_peak(time, dev, beta: float = 5.0):
    w = jax.nn.softmax(beta * dev)
    return jnp.sum(w * time)


def soft_recovery_time(time, dev, start, threshold, width: float = 0.1):
    """Integral after ``start`` of sigmoid((d - threshold) / (width * threshold)) dt."""
    dt = time[1] - time[0]
    gate = jax.nn.sigmoid((time - start) / dt)
    above = jax.nn.sigmoid((dev - threshold) / (width * threshold))
    return jnp.sum(gate * above) * dt


def soft_overshoot(time, dev, t_return, beta: float = 5.0):
    """Smooth peak of the deviation after the (soft) return time ``t_return``."""
    gate = jax.nn.sigmoid((time - t_return) / (time[1] - time[0]))
    return soft_peak(dev * gate, beta)
