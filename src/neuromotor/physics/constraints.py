"""The constraint rows of Eq. 2 and post-stabilization (Cline & Pai 2003).

J stacks the rows of Eq. 1 (the driven root's 6 rows, unless the root floats free, and 3 rows
per ball joint) and 3 rows per driven joint (relative angular velocity of child and parent).
``b`` is their prescribed velocity (Eq. 2's second block row) and ``C(x)`` their position-level
error. Post-stabilization projects positions back onto ``C(x) = 0`` in the metric of M,

    (J M^-1 J^T) mu = -C(x),      x <- x (+) M^-1 J^T mu,

solved by the chosen solver (:meth:`~neuromotor.physics.solvers.base.KKTSolver.projection_step`),
then closes what that linearized step leaves (about 1e-8 m, from turning bodies by the exponential
map) by further Newton steps that only move each subtree by its joint's gap
(:func:`closing_step`), a fixed number in all (so the step stays differentiable in both modes).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from neuromotor.model.skeleton import Model
from neuromotor.physics.solvers import nullspace
from neuromotor.physics.system import constraint_error, joint_levers, retract, root_lever
from neuromotor.rotations import mm, mv, quat_to_matrix, rotation_error


class PoseTargets(eqx.Module):
    """What post-stabilization projects onto: the driven root's pose and the driven joints'
    relative rotations, at one grid time."""

    root_origin: Float[Array, 3]
    root_rot: Float[Array, "3 3"]
    rel_rot: Float[Array, "B 3 3"]  # each body's desired rotation in its parent's frame


def constraint_count(model: Model, driven: tuple[int, ...], free_root: bool) -> int:
    """Rows of :func:`~neuromotor.physics.system.full_constraints`."""
    return model.n_constraints - (6 if free_root else 0) + 3 * len(driven)


def full_constraint_error(
    model: Model, driven: tuple[int, ...], pos, rot, targets: PoseTargets, free_root: bool = False
) -> Float[Array, " nc"]:
    """C(x) over the rows of :func:`~neuromotor.physics.system.full_constraints`."""
    err = constraint_error(model, pos, rot, targets.root_origin, targets.root_rot)[6 if free_root else 0 :]
    if not driven:
        return err
    drv = jnp.array(driven)
    par = jnp.array([model.body_parent[b] for b in driven])
    target = mm(rot[par], targets.rel_rot[drv])
    extra = rotation_error(rot[drv], target).reshape(-1)
    return jnp.concatenate([err, extra])


def constraint_velocity(
    model: Model, driven: tuple[int, ...], rot, root_vel, root_omega, rel_omega, free_root: bool = False
) -> Float[Array, " nc"]:
    """b of Eq. 2: driven root origin velocity and angular velocity, driven joints' rates."""
    b = jnp.zeros(model.n_constraints, rot.dtype)
    b = b.at[0:3].set(root_vel).at[3:6].set(root_omega)[6 if free_root else 0 :]
    if not driven:
        return b
    par = jnp.array([model.body_parent[bb] for bb in driven])
    extra = mv(rot[par], rel_omega[jnp.array(driven)]).reshape(-1)
    return jnp.concatenate([b, extra])


def closing_step(model: Model, cfg, rot, c: Float[Array, " nc"], unrolled: bool = False) -> Float[Array, "B 6"]:
    """A dx with ``J dx = -C`` and no solve: each subtree moves by its joint's gap, the root and
    the driven joints turn by their errors (:func:`~neuromotor.physics.solvers.nullspace.particular_correction`).
    Not of least M-norm, so post-stabilization uses it only after the projection, where C is
    about 1e-8 m and the metric no longer shows (Ascher et al. 1995: any correction F with
    ``J F = 1`` keeps the iteration's convergence). ``unrolled``: the batched form of the sums."""
    st = nullspace.structure(model.topology, cfg.driven, cfg.free_root, unrolled)
    geo = nullspace.geometry(st, *joint_levers(model, rot), root_lever(model, rot))
    return nullspace.particular_correction(st, geo, c)


def post_stabilize(model: Model, cfg, solver, pos, quat, targets: PoseTargets):
    """Project positions onto the constraint manifold in ``cfg.stabilization_steps`` Newton steps:
    the first ``dx = M^-1 J^T mu`` with ``J dx = -C`` solved by ``solver``, the later ones
    :func:`closing_step` (J and C of every iterate, so J dx = -C holds at each). Returns the
    positions, orientations and the constraint error left. (Why a closing step rather than a
    second projection, and what it changes: docs/benchmarks.md, issue 17.)"""
    for i in range(cfg.stabilization_steps):  # a fixed, small number of Newton steps (unrolled)
        rot = quat_to_matrix(quat)
        c = full_constraint_error(model, cfg.driven, pos, rot, targets, cfg.free_root)
        dx = solver.projection_step(model, cfg, rot, c) if i == 0 else closing_step(model, cfg, rot, c, solver.unrolled)
        pos, quat = retract(pos, quat, dx)
    rot = quat_to_matrix(quat)
    return pos, quat, full_constraint_error(model, cfg.driven, pos, rot, targets, cfg.free_root)
