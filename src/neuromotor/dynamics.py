"""Forward dynamics (Eq. 2): a linearly implicit step, post-stabilization, and the rollout.

One step from t to t + h (Anitescu & Potra's linearly implicit scheme, Section 4.1):

    [ M - h D - h^2 K   -J^T ] [ v+  ]   [ M v + h (k - D v) ]
    [       J             0  ] [ lam ] = [       b(t+h)      ]          (2)

with k = f_ext + H^T (tau + feedback) + perturbations, K = dk/dx over the position tangent space
(3 translations and 3 world-frame rotations per body) and D = dk/dv, both by ``jax.jacfwd``.
Only the stiff forces -- muscle torques and the gyroscopic term -- depend on the state, and
both are pure torques that depend on orientations and angular velocities only, so K and D live
in the angular-angular blocks. b carries the driven root's (and driven joints') velocity.
Positions then move with v+ (quaternions by the exponential map) and are projected back onto
the constraint manifold (Cline & Pai 2003): ``(J M^-1 J^T) mu = -C(x)``, ``x <- x + M^-1 J^T mu``,
a fixed number of Newton iterations so the step stays differentiable in both modes.

The rollout is one ``lax.scan``; divergence is recorded in the carry (first bad step and body)
and raised on the host by :func:`check_rollout`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .control import Gains, feedback_multipliers, joint_torque_magnitude
from .inverse import inverse_dynamics, mocap_angles, sim_columns
from .kinematics import Trajectory, body_kinematics
from .perturbation import ForcePulses, generalized_forces, no_pulses
from .rotations import (
    matrix_to_quat,
    quat_log,
    quat_exp,
    quat_mul,
    quat_normalize,
    quat_to_matrix,
    rotation_error,
)
from .skeleton import Model
from .system import (
    State,
    constraint_error,
    constraint_jacobian,
    dof_axes,
    gravity_forces,
    gyroscopic_forces,
    joint_angles,
    joint_rates,
    mass_matrix,
    muscle_jacobian,
    relative_rotations,
)


class SimulationDiverged(RuntimeError):
    """Raised when a rollout blows up; names the step, the time and the body."""

    def __init__(self, step: int, time: float, body: str, reason: str = "non-finite or runaway state"):
        self.step, self.time, self.body = step, time, body
        super().__init__(f"simulation diverged at step {step} (t = {time:.4f} s) in body {body!r}: {reason}")


class SimConfig(eqx.Module):
    """Static settings of a rollout."""

    h: float = eqx.field(static=True, default=1.0 / 120.0)
    n_steps: int = eqx.field(static=True, default=120)
    driven: tuple[int, ...] = eqx.field(static=True, default=())  # bodies driven along the mocap
    implicit: bool = eqx.field(static=True, default=True)  # False: K = D = 0 (explicit forces)
    stab_iters: int = eqx.field(static=True, default=3)
    max_speed: float = eqx.field(static=True, default=200.0)  # rad/s or m/s: beyond it, diverged
    free_root: bool = eqx.field(static=True, default=False)  # drop the 6 driven-root rows


class Reference(eqx.Module):
    """Mocap targets on the simulation grid t_k = t0 + k h, k = 0..S."""

    time: Float[Array, " S1"]
    tau: Float[Array, "S1 n"]  # feedforward multipliers (Eq. 3)
    activation: Float[Array, "S1 n"]  # |T_j| of each DOF's joint (see control)
    theta: Float[Array, "S1 n"]  # desired Euler angles theta_d
    theta_dot: Float[Array, "S1 n"]
    root_origin: Float[Array, "S1 3"]
    root_rot: Float[Array, "S1 3 3"]
    root_vel: Float[Array, "S1 3"]
    root_omega: Float[Array, "S1 3"]
    rel_rot: Float[Array, "S1 B 3 3"]  # each body's desired rotation in its parent's frame
    rel_omega: Float[Array, "S1 B 3"]  # desired relative angular velocity, parent frame
    init: State


def make_reference(model: Model, traj: Trajectory, t0: float, h: float, n_steps: int) -> Reference:
    times = t0 + h * jnp.arange(n_steps + 1)
    q = jax.vmap(traj.q)(times)
    qd = jax.vmap(traj.qd)(times)
    qdd = jax.vmap(traj.qdd)(times)
    kin = jax.vmap(lambda a, b, c: body_kinematics(model, a, b, c))(q, qd, qdd)
    pos, rot, vel, omega = kin[0], kin[1], kin[2], kin[3]
    theta, theta_dot, _ = jax.vmap(lambda t: mocap_angles(model, traj, t))(times)
    cols = sim_columns(model)
    sol = inverse_dynamics(model, traj, times)
    activation = joint_torque_magnitude(model, sol.axes, sol.tau)
    par = jnp.array([max(p, 0) for p in model.body_parent], dtype=jnp.int32)
    rel = jnp.swapaxes(rot[:, par], -1, -2) @ rot
    rel_w = jnp.einsum("tbji,tbj->tbi", rot[:, par], omega - omega[:, par])
    init = State(pos[0], matrix_to_quat(rot[0]), vel[0], omega[0])
    root_origin = pos[:, 0] - jnp.einsum("tij,j->ti", rot[:, 0], model.com[0])
    return Reference(times, sol.tau, activation, theta[:, cols], theta_dot[:, cols], root_origin,
                     rot[:, 0], qd[:, 0:3], omega[:, 0], rel, rel_w, init)


def _active_mask(model: Model, driven: tuple[int, ...], dtype) -> Float[Array, " n"]:
    return jnp.array([0.0 if b in driven else 1.0 for b in model.dof_body], dtype)


DAMPING = 0.02  # damped least squares at gimbal lock (singular value scale of the Euler axes)


def damped_solve(a: Float[Array, "3 3"], e: Float[Array, " 3"], mu: float = DAMPING):
    """x = A^T (A A^T + mu^2 I)^-1 e: A^-1 e away from singularity, bounded at gimbal lock."""
    return a.T @ jnp.linalg.solve(a @ a.T + mu**2 * jnp.eye(3, dtype=a.dtype), e)


def dof_errors(model: Model, rot, omega, axes, rel_d, rel_w_d):
    """Per-DOF angle and rate errors (desired minus simulated) from rotation errors.

    The joint's rotation error (rotation vector taking the simulated relative orientation to
    the desired one, world frame) and relative angular-velocity error are resolved along the
    Euler axes h_i. To first order this is exactly theta_d - theta and thetadot_d - thetadot of
    the BVH decomposition, it is always the shortest rotation (no wrapping issue), and it stays
    bounded at gimbal lock, where Euler differences are ill-defined.
    """
    par = jnp.array([max(p, 0) for p in model.body_parent])
    rel = jnp.swapaxes(rot[par], -1, -2) @ rot
    e_local = quat_log(matrix_to_quat(rel_d @ jnp.swapaxes(rel, -1, -2)))
    e_world = jnp.einsum("bij,bj->bi", rot[par], e_local)
    w_err = jnp.einsum("bij,bj->bi", rot[par], rel_w_d) - (omega - omega[par])
    d_theta, d_rate = [], []
    for b in range(1, model.n_bodies):
        dofs = jnp.array(model.dofs_of_body(b))
        a = axes[dofs].T
        d_theta.append(damped_solve(a, e_world[b]))
        d_rate.append(damped_solve(a, w_err[b]))
    return jnp.concatenate(d_theta), jnp.concatenate(d_rate)


def muscle_and_gyro(model: Model, gains: Gains, ref_k, active, rot, omega):
    """Stiff generalized forces: muscle torques (feedforward + feedback) and gyroscopic term.

    The Euler axes h_i come from the desired joint angles placed in the simulated parent's
    frame: exactly Eq. 4 on the mocap, and the feedforward sum h_i tau_i stays well-conditioned
    near gimbal lock where the individual tau_i are large and of opposite signs.
    """
    tau, act, theta_d, rel_d, rel_w_d = ref_k
    axes = dof_axes(model, rot, theta_d)
    d_theta, d_rate = dof_errors(model, rot, omega, axes, rel_d, rel_w_d)
    mult = feedback_multipliers(gains, tau, act, d_theta, d_rate, active)
    return gyroscopic_forces(model, rot, omega) + muscle_jacobian(model, axes).T @ mult


def _rotate(delta: Float[Array, "B 3"], rot: Float[Array, "B 3 3"]) -> Float[Array, "B 3 3"]:
    return quat_to_matrix(quat_exp(delta)) @ rot


def stiff_jacobians(model, gains, ref_k, active, rot, omega):
    """k_stiff, K and D restricted to angular coordinates: (6B,), (6B, 3B), (6B, 3B)."""
    n = model.n_bodies

    def f(delta, w):
        return muscle_and_gyro(model, gains, ref_k, active, _rotate(delta, rot), w)

    zero = jnp.zeros((n, 3), rot.dtype)
    k = f(zero, omega)
    kmat = jax.jacfwd(f, argnums=0)(zero, omega).reshape(6 * n, 3 * n)
    dmat = jax.jacfwd(f, argnums=1)(zero, omega).reshape(6 * n, 3 * n)
    return k, kmat, dmat


def _angular_embed(mat: Float[Array, "N 3B"], n: int) -> Float[Array, "N 6B"]:
    """Place columns over angular coordinates into the full 6B layout."""
    out = jnp.zeros((mat.shape[0], n, 6), mat.dtype)
    out = out.at[:, :, 3:].set(mat.reshape(mat.shape[0], n, 3))
    return out.reshape(mat.shape[0], 6 * n)


def full_constraints(model: Model, driven: tuple[int, ...], rot, free_root: bool = False) -> Float[Array, "nc 6B"]:
    """J with extra rows for driven joints (relative angular velocity of child and parent);
    without the 6 root rows when the root floats free."""
    jac = constraint_jacobian(model, rot)[6 if free_root else 0:]
    if not driven:
        return jac
    n = model.n_bodies
    rows = jnp.zeros((3 * len(driven), 6 * n), rot.dtype)
    eye = jnp.eye(3, dtype=rot.dtype)
    for i, b in enumerate(driven):
        p = model.body_parent[b]
        rows = rows.at[3 * i:3 * i + 3, 6 * b + 3:6 * b + 6].set(eye)
        rows = rows.at[3 * i:3 * i + 3, 6 * p + 3:6 * p + 6].set(-eye)
    return jnp.concatenate([jac, rows], 0)


def full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root=False):
    err = constraint_error(model, pos, rot, root_origin, root_rot)[6 if free_root else 0:]
    if not driven:
        return err
    drv = jnp.array(driven)
    par = jnp.array([model.body_parent[b] for b in driven])
    target = rot[par] @ rel_rot[drv]
    extra = rotation_error(rot[drv], target).reshape(-1)
    return jnp.concatenate([err, extra])


def constraint_velocity(model, driven, rot, root_vel, root_omega, rel_omega, free_root=False):
    """b of Eq. 2: driven root origin velocity and angular velocity, driven joints' rates."""
    b = jnp.zeros(model.n_constraints, rot.dtype)
    b = b.at[0:3].set(root_vel).at[3:6].set(root_omega)[6 if free_root else 0:]
    if not driven:
        return b
    par = jnp.array([model.body_parent[bb] for bb in driven])
    extra = jnp.einsum("dij,dj->di", rot[par], rel_omega[jnp.array(driven)]).reshape(-1)
    return jnp.concatenate([b, extra])


def inverse_mass_blocks(model: Model, rot):
    inv_i = rot @ jnp.linalg.inv(model.inertia) @ jnp.swapaxes(rot, -1, -2)
    return 1.0 / model.mass, inv_i


def apply_inverse_mass(model, rot, g: Float[Array, "... 6B"]):
    inv_m, inv_i = inverse_mass_blocks(model, rot)
    g = g.reshape(g.shape[:-1] + (model.n_bodies, 6))
    lin = g[..., :3] * inv_m[:, None]
    ang = jnp.einsum("bij,...bj->...bi", inv_i, g[..., 3:])
    return jnp.concatenate([lin, ang], -1).reshape(g.shape[:-2] + (6 * model.n_bodies,))


def post_stabilize(model: Model, driven, pos, quat, targets, iters: int, free_root: bool = False):
    """Project positions onto the constraint manifold (Cline & Pai 2003), fixed Newton steps."""
    root_origin, root_rot, rel_rot = targets

    def body(carry, _):
        pos, quat = carry
        rot = quat_to_matrix(quat)
        c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
        jac = full_constraints(model, driven, rot, free_root)
        minv_jt = apply_inverse_mass(model, rot, jac).T  # (6B, nc)
        mu = jnp.linalg.solve(jac @ minv_jt, -c)
        delta = (minv_jt @ mu).reshape(model.n_bodies, 6)
        pos = pos + delta[:, :3]
        quat = quat_normalize(quat_mul(quat_exp(delta[:, 3:]), quat))
        return (pos, quat), None

    (pos, quat), _ = jax.lax.scan(body, (pos, quat), None, length=iters)
    rot = quat_to_matrix(quat)
    c = full_constraint_error(model, driven, pos, rot, root_origin, root_rot, rel_rot, free_root)
    return pos, quat, c


class StepInfo(eqx.Module):
    residual: Float[Array, ""]  # relative residual of the KKT solve of Eq. 2
    violation: Float[Array, ""]  # max |C(x)| after post-stabilization (m or rad)
    force: Float[Array, "B 3"]  # perturbation force per body (world, N)
    points: Float[Array, "P 3"]  # world application points of the pulses
    lam: Float[Array, " nc"]


def step(model: Model, gains: Gains, pulses: ForcePulses, cfg: SimConfig, ref: Reference, k, state: State):
    """One linearly implicit step from t_k to t_k + h (Eq. 2 plus post-stabilization)."""
    h = cfg.h
    n = model.n_bodies
    rot = state.rot
    active = _active_mask(model, cfg.driven, rot.dtype)
    ref_k = (ref.tau[k], ref.activation[k], ref.theta[k], ref.rel_rot[k], ref.rel_omega[k])
    t = ref.time[k]
    if cfg.implicit:
        k_stiff, kmat, dmat = stiff_jacobians(model, gains, ref_k, active, rot, state.omega)
        kmat, dmat = _angular_embed(kmat, n), _angular_embed(dmat, n)
    else:
        k_stiff = muscle_and_gyro(model, gains, ref_k, active, rot, state.omega)
        kmat = dmat = jnp.zeros((6 * n, 6 * n), rot.dtype)
    gravity = gravity_forces(model)
    f_pert, per_body, points = generalized_forces(pulses, t, n, state.pos, rot, model.com)
    kvec = k_stiff + gravity + f_pert
    m = mass_matrix(model, rot)
    jac = full_constraints(model, cfg.driven, rot, cfg.free_root)
    nc = jac.shape[0]
    v = state.v
    a11 = m - h * dmat - h * h * kmat
    lhs = jnp.block([[a11, -jac.T], [jac, jnp.zeros((nc, nc), rot.dtype)]])
    b = constraint_velocity(model, cfg.driven, rot, ref.root_vel[k + 1], ref.root_omega[k + 1],
                            ref.rel_omega[k + 1], cfg.free_root)
    rhs = jnp.concatenate([m @ v + h * (kvec - dmat @ v), b])
    sol = jnp.linalg.solve(lhs, rhs)
    residual = jnp.linalg.norm(lhs @ sol - rhs) / jnp.maximum(jnp.linalg.norm(rhs), 1e-300)
    v_new = sol[: 6 * n].reshape(n, 6)
    vel, omega = v_new[:, :3], v_new[:, 3:]
    pos = state.pos + h * vel
    quat = quat_normalize(quat_mul(quat_exp(h * omega), state.quat))
    targets = (ref.root_origin[k + 1], ref.root_rot[k + 1], ref.rel_rot[k + 1])
    pos, quat, c = post_stabilize(model, cfg.driven, pos, quat, targets, cfg.stab_iters, cfg.free_root)
    info = StepInfo(residual, jnp.max(jnp.abs(c)) if c.size else jnp.zeros((), rot.dtype), per_body, points, sol[6 * n:] / h)
    return State(pos, quat, vel, omega), info


class Rollout(eqx.Module):
    """States at t_0..t_S, simulated joint angles, and per-step diagnostics."""

    time: Float[Array, " S1"]
    states: State  # leaves with leading axis S+1
    theta: Float[Array, "S1 n"]
    theta_dot: Float[Array, "S1 n"]
    residual: Float[Array, " S"]
    violation: Float[Array, " S"]
    force: Float[Array, "S1 B 3"]
    points: Float[Array, "S1 P 3"]
    diverged_step: Int[Array, ""]  # -1 if the run stayed finite
    diverged_body: Int[Array, ""]


def _badness(state: State, max_speed: float):
    finite = (jnp.all(jnp.isfinite(state.pos), -1) & jnp.all(jnp.isfinite(state.quat), -1)
              & jnp.all(jnp.isfinite(state.vel), -1) & jnp.all(jnp.isfinite(state.omega), -1))
    speed = jnp.maximum(jnp.linalg.norm(state.vel, axis=-1), jnp.linalg.norm(state.omega, axis=-1))
    score = jnp.where(finite, speed / max_speed, jnp.inf)
    return score


def observe(model: Model, state: State, ref: Reference, k):
    rot = state.rot
    theta = joint_angles(model, rot, reference=ref.theta[k])
    axes = dof_axes(model, rot, theta)
    return theta, joint_rates(model, axes, state.omega)


def rollout(model: Model, gains: Gains, pulses: ForcePulses, ref: Reference, cfg: SimConfig) -> Rollout:
    """Simulate ``cfg.n_steps`` steps from the reference's initial state (one ``lax.scan``)."""
    if ref.time.shape[0] < cfg.n_steps + 1:
        raise ValueError(f"reference has {ref.time.shape[0] - 1} steps, config asks for {cfg.n_steps}")
    if pulses is None:
        pulses = no_pulses()

    def body(carry, k):
        state, bad_step, bad_body = carry
        new, info = step(model, gains, pulses, cfg, ref, k, state)
        score = _badness(new, cfg.max_speed)
        is_bad = jnp.max(score) > 1.0
        first = is_bad & (bad_step < 0)
        bad_step = jnp.where(first, k, bad_step)
        bad_body = jnp.where(first, jnp.argmax(score), bad_body)
        # After a blow-up keep the last good state so NaNs do not spread through the batch.
        new = jax.tree_util.tree_map(lambda a, b: jnp.where(bad_step >= 0, a, b), state, new)
        theta, theta_dot = observe(model, new, ref, k + 1)
        return (new, bad_step, bad_body), (new, theta, theta_dot, info)

    init = ref.init
    carry0 = (init, jnp.asarray(-1), jnp.asarray(-1))
    (_, bad_step, bad_body), (states, theta, theta_dot, info) = jax.lax.scan(
        body, carry0, jnp.arange(cfg.n_steps)
    )
    theta0, theta_dot0 = observe(model, init, ref, 0)
    stack = lambda a, b: jnp.concatenate([a[None], b], 0)
    states = jax.tree_util.tree_map(stack, init, states)
    _, f0, p0 = generalized_forces(pulses, ref.time[0], model.n_bodies, init.pos, init.rot, model.com)
    return Rollout(
        ref.time[: cfg.n_steps + 1],
        states,
        stack(theta0, theta),
        stack(theta_dot0, theta_dot),
        info.residual,
        info.violation,
        stack(f0, info.force),
        stack(p0, info.points),
        bad_step,
        bad_body,
    )


def check_rollout(model: Model, run: Rollout) -> Rollout:
    """Raise :class:`SimulationDiverged` (step, time, body) if the rollout blew up."""
    step_ = int(run.diverged_step)
    if step_ >= 0:
        raise SimulationDiverged(step_, float(run.time[step_ + 1]), model.body_names[int(run.diverged_body)])
    return run
