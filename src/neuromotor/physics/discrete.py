"""Discrete-time inverse dynamics: the feedforward that makes the forward step replay the capture.

Eq. 3 gives the torques of the continuous equations of motion along the spline. The forward
step (Eq. 2, post-stabilization) is a discrete map, so those torques leave an O(h) error per step
that the low-gain feedback must absorb: degrees on fast motions. Here the feedforward is the
exact inverse of the step instead (as MuJoCo's discrete inverse dynamics inverts its own
integrator): torque multipliers tau_k such that one step from the capture's state at t_k lands
on the capture's state at t_k+1.

1. **Velocities** (:func:`landing_velocities`). The step's velocity v+ obeys the velocity
   constraints at x_k (``J(x_k) v+ = b``) and its positions are ``x_k (+) h v+`` projected back
   onto the constraints. For each step the velocity u_k+1 with ``J(x_k) u = b`` that lands on
   the capture's pose x_k+1 after that projection is found by a fixed-point iteration on the
   bodies' angular velocities (linear velocities follow from the joint rows; the root's from
   its finite difference): each round turns every body by its remaining rotation error over h.
   It depends on the poses only, so every step is solved on its own.
2. **Torques** (:func:`step_feedforward`). With v = u_k and v+ = u_k+1 known, the first block row
   of Eq. 2 is linear in the multipliers: on the capture the controller's errors are zero (its
   rate targets are the same u_k, :func:`neuromotor.physics.dynamics.make_reference`), and the
   feedback's implicit terms cancel against its drift with the reference
   (:func:`neuromotor.physics.stiffness.reference_drift`), so only the gyroscopic term's K and D
   and the feedforward's own turn with the parent remain:

       [J^T  H'^T] [lam; tau] = M (u+ - u) / h - D_g (u+ - u) - h K_g u+ - f_ext,
       h'_i = h_i + h w_parent(u+) x h_i     (active joints, implicit step).

   It is square like Eq. 3 and does not depend on the gains, so the reference stays fixed while
   a fit or a sweep varies them.
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from neuromotor import compiler
from neuromotor.model.skeleton import Model
from neuromotor.physics import solvers
from neuromotor.physics.constraints import PoseTargets, post_stabilize
from neuromotor.physics.inverse import eq3_matrix
from neuromotor.physics.stiffness import gyro_blocks
from neuromotor.physics.system import (
    gravity_forces,
    joint_levers,
    mass_times,
    per_joint_to_dofs,
    retract,
    world_inertia,
)
from neuromotor.rotations import cross, mm, mv, quat_conj, quat_log, quat_mul, quat_to_matrix

LANDING_TOLERANCE = 1e-14  # rad: rotation left between the landed pose and the capture
LANDING_ITERATIONS = 30


class DiscreteInverse(eqx.Module):
    """The discrete inverse dynamics of a grid: velocities, feedforward and their convergence."""

    velocity: Float[Array, "S1 B 6"]  # u_k per body [linear, angular] (u_0: the spline's)
    tau: Float[Array, "S n"]  # feedforward multipliers of step k
    lam: Float[Array, "S nc"]  # constraint impulses over h (root, then 3 per ball joint)
    residual: Float[Array, " S"]  # relative residual of the square solve of step k
    landing: Float[Array, " S"]  # rotation (rad) left between the landed pose and the capture
    iterations: Int[Array, " S"]  # fixed-point rounds of the landing velocity


def _ancestor_joints(model: Model) -> jnp.ndarray:
    """(B, C): 1 where joint row c lies on the path from the root to body b."""
    topo = model.topology
    return jnp.asarray(topo.anc[:, topo.child], jnp.float64)


def landing_velocity(model: Model, cfg, p0, q0, p1, q1, targets: PoseTargets):
    """``(u, rotation left, rounds)``: the velocity that carries the pose (p0, q0) onto (p1, q1)
    through the step's position update and post-stabilization (``cfg``: h, solver, driven
    joints, Newton steps), with ``J(x_0) u = b``."""
    h, topo = cfg.h, model.topology
    solver = solvers.get(cfg.solver)
    r_p, r_c = joint_levers(model, quat_to_matrix(q0))
    paths = _ancestor_joints(model).astype(p0.dtype)
    v_root = (p1[0] - p0[0]) / h

    def velocity(w):  # the joint rows of J give every body's linear velocity
        t = cross(w[topo.parent], r_p) - cross(w[topo.child], r_c)
        return jnp.concatenate([v_root + paths @ t, w], -1)

    def body(carry):
        w, it, _ = carry
        pos, quat = retract(p0, q0, h * velocity(w))
        _, quat, _ = post_stabilize(model, cfg, solver, pos, quat, targets)
        delta = quat_log(quat_mul(q1, quat_conj(quat))).at[0].set(0.0)  # the root lands by its difference
        return w + delta / h, it + 1, jnp.max(jnp.abs(delta))

    def cond(carry):
        _, it, err = carry
        return (err > LANDING_TOLERANCE) & (it < LANDING_ITERATIONS)

    w0 = quat_log(quat_mul(q1, quat_conj(q0))) / h
    w, it, err = jax.lax.while_loop(cond, body, (w0, jnp.asarray(0), jnp.asarray(jnp.inf, p0.dtype)))
    # err: the last round's correction, a bound on what the returned velocity leaves (the
    # iteration contracts; tests measure the landing itself).
    return velocity(w), err, it


def step_rhs(model: Model, cfg, rot, u0: Float[Array, "B 6"], u1: Float[Array, "B 6"]) -> Float[Array, "B 6"]:
    """The right side of the step's first block row per body (module docstring, item 2):
    ``M (u+ - u) / h - D_g (u+ - u) - h K_g u+ - f_ext`` (force, torque about the COM; world).
    Its sum over the bodies (torques moved to one point) is the wrench the driven root must
    carry: the joints' rows and the torques cancel in it (:mod:`neuromotor.physics.grf`)."""
    h = cfg.h
    inertia = world_inertia(model, rot)
    w0, w1 = u0[:, 3:], u1[:, 3:]
    rhs = mass_times(model, inertia, u1 - u0) / h - gravity_forces(model).reshape(-1, 6)
    gyro, blocks = gyro_blocks(model, rot, w0)
    ang = -gyro
    if cfg.implicit:
        ang = ang - mv(blocks[..., 3:], w1 - w0) - h * mv(blocks[..., :3], w1)
    return rhs.at[:, 3:].add(ang)


def step_feedforward(
    model: Model,
    cfg,
    local_axes: Float[Array, "C 3 3"],
    active: Float[Array, "C 3"],
    pos,
    quat,
    u0: Float[Array, "B 6"],
    u1: Float[Array, "B 6"],
    external: Float[Array, "B 6"] | None = None,
):
    """``(tau, lam, relative residual)`` of one step: the multipliers that make Eq. 2 at the
    pose (pos, quat) with velocity u0 give v+ = u1 (module docstring). ``external``: known
    forces on the bodies over the step (force, torque about the COM; world), such as ground
    reaction forces; they join f_ext."""
    h, topo = cfg.h, model.topology
    rot = quat_to_matrix(quat)
    rhs = step_rhs(model, cfg, rot, u0, u1)
    if external is not None:
        rhs = rhs - external
    rhs = rhs.reshape(-1)
    axes = jnp.swapaxes(mm(rot[topo.parent], local_axes), -1, -2)  # (C, slot, 3): world h_i as rows
    if cfg.implicit:
        axes = axes + h * active[..., None] * cross(u1[topo.parent, 3:][:, None, :], axes)
    lhs = eq3_matrix(model, rot, per_joint_to_dofs(model, axes))
    x = jnp.linalg.solve(lhs, rhs)
    residual = jnp.linalg.norm(lhs @ x - rhs) / jnp.maximum(jnp.linalg.norm(rhs), 1e-300)
    nc = model.n_constraints
    return x[nc:], x[:nc], residual


LANDING_BLOCK = 64  # steps per compiled call: one program per skeleton and step options, any window


@functools.partial(compiler.jit, static_argnames=("cfg",))
def _landing_block(model: Model, cfg, p0, q0, p1, q1, targets: PoseTargets):
    # lax.map, not vmap: a loop of one step's program traces and compiles in about half the
    # time of its batched twin, and the iteration count of each step is its own.
    return jax.lax.map(lambda x: landing_velocity(model, cfg, *x), (p0, q0, p1, q1, targets))


def landing_velocities(
    model: Model, cfg, pos: Float[Array, "S1 B 3"], quat: Float[Array, "S1 B 4"], targets: PoseTargets
):
    """:func:`landing_velocity` of every step of the grid: ``(u (S, B, 6), rotation left (S,),
    rounds (S,))``. Run in blocks of :data:`LANDING_BLOCK` steps by one program compiled for the
    skeleton and the step's options but not the window's length (the last block padded with
    its own last step), so windows of any length share it (and the persistent compile cache)."""
    n = pos.shape[0] - 1
    key = dataclasses.replace(cfg, n_steps=0)  # the block's program does not depend on the window
    pad = (-n) % LANDING_BLOCK
    grow = lambda a, lo, hi: jnp.concatenate([a[lo:hi], jnp.repeat(a[hi - 1 : hi], pad, 0)], 0)
    args = (
        grow(pos, 0, n),
        grow(quat, 0, n),
        grow(pos, 1, n + 1),
        grow(quat, 1, n + 1),
        jax.tree_util.tree_map(lambda a: grow(a, 1, n + 1), targets),
    )
    parts = [
        _landing_block(model, key, *jax.tree_util.tree_map(lambda a: a[i : i + LANDING_BLOCK], args))
        for i in range(0, n + pad, LANDING_BLOCK)
    ]
    return tuple(jnp.concatenate(x, 0)[:n] for x in zip(*parts))


def discrete_inverse_dynamics(
    model: Model,
    cfg,
    pos: Float[Array, "S1 B 3"],
    quat: Float[Array, "S1 B 4"],
    u_start: Float[Array, "B 6"],
    targets: PoseTargets,
    local_axes: Float[Array, "S1 C 3 3"],
    active: Float[Array, "C 3"],
    landed=None,
) -> DiscreteInverse:
    """:class:`DiscreteInverse` of the capture's poses on the grid (``targets``: the pose targets
    of every grid time, as post-stabilization reads them; ``u_start``: the velocity at t_0;
    ``landed``: :func:`landing_velocities`' output if already computed, else computed here)."""
    if cfg.free_root:
        raise ValueError("discrete inverse dynamics needs the driven root (the paper's model)")
    u, landing, rounds = landing_velocities(model, cfg, pos, quat, targets) if landed is None else landed
    velocity = jnp.concatenate([u_start[None], u], 0)
    tau, lam, residual = jax.vmap(lambda la, p, q, a, b: step_feedforward(model, cfg, la, active, p, q, a, b))(
        local_axes[:-1], pos[:-1], quat[:-1], velocity[:-1], velocity[1:]
    )
    return DiscreteInverse(velocity, tau, lam, residual, landing, rounds)
