"""The delayed stretch reflex: the spinal and long-latency feedback paths of Section 3 (Figure 1)
that the paper leaves to future work (Section 7).

The paper's controller (Section 5.2, :mod:`neuromotor.physics.control`) keeps only the muscle
feedback, which acts without delay and enters K and D of Eq. 2. Here two more paths act on every
simulated DOF i, each on what the joint did ``d`` seconds ago:

    u_i(t)   = e_i(t) + c edot_i(t)                              (stretch signal, rad)
    r_i(t)   = m_i(t) s_i [ g_s U_i(t - d_s) + g_l U_i(t - d_l) ]  (reflex multiplier)
    rho_j    = sum over the DOFs of joint j of h_i r_i            (joint torque, N m)

with ``e = theta_d - theta`` and ``edot`` the angle and rate errors of
:func:`neuromotor.physics.control.joint_errors` (the same errors as the muscle feedback), ``c``
the rate weight (s), ``m_i = max(|T_j|, floor)`` and ``s_i = I_j / rms|T_j|`` the signal
dependence and distal-inertia scaling of the muscle feedback (so one gain sets every joint and
the gains ``g`` are in 1/s^2 like ks), and ``g_s, d_s`` the spinal (short-latency) and
``g_l, d_l`` the long-latency (supraspinal) gain and delay. ``U`` is ``u``, or with
``one_sided = 1`` only the part that stretches the loaded muscle of the DOF's pair: with
``sigma = tanh(tau_i / (0.1 rms|T_j|))`` the smooth sign of the feedforward torque,
``U = sigma ramp(sigma u)`` where ``ramp(x) = x sigmoid(x / w)`` is a smooth max(x, 0) of width
``w``; ``one_sided`` between 0 and 1 blends the two.

Delays. The errors of every step are pushed into a fixed-length buffer in the ``lax.scan``
carry (:class:`History`, index 0 the current step). A delay ``d = (m + f) h`` reads
``(1 - f) e[m] + f e[m + 1]``: linear interpolation between grid steps, so the rollout is
differentiable with respect to the delay as well as the gains. The delayed terms are known
when the step starts, so ``rho`` enters the force vector k of Eq. 2 and leaves K and D alone
(a delay of zero therefore gives the explicit form of the muscle feedback term). Before the
first step the history holds zero error (the character followed the mocap).

Literature defaults (:data:`SPINAL_DELAY`, :data:`LONG_LATENCY_DELAY`): the short-latency
(monosynaptic, M1) stretch reflex of the arm and leg answers in about 25-50 ms and the
long-latency (M2/M3, transcortical) response in about 50-100 ms (Lee & Tatton 1975, Can. J.
Neurol. Sci. 2:285; Matthews 1991, Trends Neurosci. 14:87; Pruszynski & Scott 2012, Exp.
Brain Res. 218:341); reflex stiffness is dominated by stretch velocity (Kearney, Stein &
Parameswaran 1997, IEEE Trans. Biomed. Eng. 44:493), hence a rate weight.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

SPINAL_DELAY = 0.04  # s: short-latency stretch reflex, 25-50 ms
LONG_LATENCY_DELAY = 0.08  # s: long-latency (transcortical) response, 50-100 ms
SPINAL_GAIN = 100.0  # 1/s^2: a quarter of the default muscle ks
RATE_WEIGHT = 0.1  # s: stretch velocity weighs as much as 0.1 s of stretch
MAX_DELAY = 0.12  # s: the history buffer covers delays up to this
DELAY_LIMIT = 1.0  # s: the longest history a config may ask for (the buffer lives in the scan carry)
RAMP_WIDTH = 0.005  # rad: width of the one-sided ramp
SIGN_WIDTH = 0.1  # the smooth sign of tau_i turns over 10 % of the joint's RMS torque


class ReflexPath(eqx.Module):
    """One delayed path: its gain (1/s^2, like ks) and delay (s)."""

    gain: Float[Array, ""]
    delay: Float[Array, ""]


class Reflex(eqx.Module):
    """The spinal and long-latency paths (array leaves: fit, sweep, vmap) and the history length."""

    spinal: ReflexPath
    long_latency: ReflexPath
    rate_weight: Float[Array, ""]  # c (s)
    one_sided: Float[Array, ""]  # 0: both directions, 1: only while the loaded muscle is stretched
    width: Float[Array, ""]  # w (rad) of the one-sided ramp
    steps: int = eqx.field(static=True)  # grid steps of error history kept (delays up to (steps - 2) h)


def make_reflex(
    h: float,
    gain=SPINAL_GAIN,
    delay=SPINAL_DELAY,
    long_gain=0.0,
    long_delay=LONG_LATENCY_DELAY,
    rate_weight=RATE_WEIGHT,
    one_sided=False,
    width=RAMP_WIDTH,
    max_delay=MAX_DELAY,
) -> Reflex:
    """A :class:`Reflex` whose history covers delays up to ``max_delay`` at step ``h``."""
    f = lambda x: jnp.asarray(x, jnp.float64)
    steps = history_steps(h, max_delay)
    return Reflex(
        ReflexPath(f(gain), f(delay)),
        ReflexPath(f(long_gain), f(long_delay)),
        f(rate_weight),
        f(float(one_sided)),
        f(width),
        steps,
    )


def history_steps(h: float, max_delay: float) -> int:
    """Buffer length: delays up to ``max_delay`` read two neighbouring entries."""
    return int(math.ceil(max_delay / h - 1e-9)) + 2


class History(eqx.Module):
    """Per-joint angle and rate errors of the last ``steps`` grid steps (index 0: the latest)."""

    angle: Float[Array, "L C 3"]
    rate: Float[Array, "L C 3"]


def empty_history(reflex: Reflex, n_joints: int, dtype) -> History:
    zeros = jnp.zeros((reflex.steps, n_joints, 3), dtype)
    return History(zeros, zeros)


def push(history: History, angle: Float[Array, "C 3"], rate: Float[Array, "C 3"]) -> History:
    """The history with this step's errors in front and the oldest dropped."""
    shift = lambda buf, x: jnp.concatenate([x[None], buf[:-1]], 0)
    return History(shift(history.angle, angle), shift(history.rate, rate))


def delayed(buffer: Float[Array, "L C 3"], delay, h: float) -> Float[Array, "C 3"]:
    """The buffered signal ``delay`` seconds ago, linearly interpolated between grid steps
    (clamped to the buffer: delays beyond ``(L - 2) h`` read the oldest pair)."""
    s = jnp.clip(delay / h, 0.0, buffer.shape[0] - 1.0)
    m = jnp.clip(jnp.floor(s), 0, buffer.shape[0] - 2)
    f = s - m
    m = jax.lax.stop_gradient(m).astype(jnp.int32)
    pair = jax.lax.dynamic_slice_in_dim(buffer, m, 2, 0)
    return (1.0 - f) * pair[0] + f * pair[1]


def stretch(reflex: Reflex, angle, rate, tau, reference_torque):
    """U of the module docstring: the (optionally one-sided) stretch signal per DOF."""
    u = angle + reflex.rate_weight * rate
    sigma = jnp.tanh(tau / (SIGN_WIDTH * reference_torque))
    x = sigma * u
    one = sigma * x * jax.nn.sigmoid(x / reflex.width)
    return (1.0 - reflex.one_sided) * u + reflex.one_sided * one


def reflex_multipliers(
    reflex: Reflex, history: History, h: float, magnitude, scale, tau, reference_torque, active=None
) -> Float[Array, "C 3"]:
    """r_i of the module docstring per joint and DOF, from the history (index 0: this step)."""
    total = jnp.zeros_like(tau)
    for path in (reflex.spinal, reflex.long_latency):
        angle = delayed(history.angle, path.delay, h)
        rate = delayed(history.rate, path.delay, h)
        total = total + path.gain * stretch(reflex, angle, rate, tau, reference_torque)
    out = magnitude * scale * total
    return out if active is None else out * active
