"""Contact-aware inverse dynamics (issue 38): ground reaction forces that explain the driven
root's wrench, the residual they leave, and the feedforward of a body on the ground.

With the root driven (the paper's model), the 6 root rows of the discrete inverse
(:mod:`neuromotor.physics.discrete`) carry whatever wrench the capture needs: the joints' rows
and the torques cancel in the sum over the bodies, so the root's multipliers equal the sum of
every body's ``M (u+ - u) / h - D_g (u+ - u) - h K_g u+ - f_ext``
(:func:`neuromotor.physics.discrete.step_rhs`), the whole body's rate of momentum less gravity.
Here, per step k (from the capture's pose x_k to x_k+1):

1. **Contact points** (:func:`capture_contacts`). The ground branch's rule for the candidates
   (``physics/contact/ground.py`` there): the vertices of each body's mass-model polyhedron,
   per body its :data:`PER_BODY` lowest, of all those the :data:`MAX_CONTACTS` lowest. A
   candidate touches the ground when it is within :data:`CONTACT_HEIGHT` of the floor at x_k
   and moves slower than :data:`CONTACT_SPEED` over the step (``|x_k+1 - x_k| / h``).
2. **Required wrench** (:func:`required_wrench`): the root's wrench as force and moment about
   the whole body's COM at x_k (world).
3. **Ground reaction forces** (:func:`solve_grf`). Forces at the touching points inside the
   ground's friction pyramid (``mu`` = :data:`FRICTION`, :data:`FRICTION_DIRECTIONS` edges on
   the Coulomb cone, as the ground's LCP), minimizing, in units of the body weight W = m g and
   the stature L,

       |F(c) - F_req|^2 / W^2 + |M(c) - M_req|^2 / (W L)^2
           + REGULARIZATION |c|^2 + SMOOTHING |c - c_prev|^2,

   with c >= 0 the edges' coefficients (over W) and c_prev the same vertex's at step k-1 (0 for
   a vertex that was not touching). A non-negative least-squares problem, solved exactly by
   ``scipy.optimize.nnls`` (Lawson-Hanson active set) on the stacked rows. The two small
   weights only choose among the forces that fit equally well (the squeeze between the feet,
   the share of each vertex): the minimum-norm split, followed with a lag of about
   ``SMOOTHING / REGULARIZATION`` steps, so the split does not jump from frame to frame.
   The residual is ``required - produced`` per step.
4. **Feedforward with the ground** (:func:`contact_feedforward`): the discrete inverse with the
   ground reaction forces as known external forces on their bodies. Its root rows then carry
   only the residual: what a free root cannot get, and the free-root simulation leaves out.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int
from scipy.optimize import nnls

from neuromotor import compiler
from neuromotor.model.skeleton import Model
from neuromotor.physics.contact.detection import facing_basis, up_direction
from neuromotor.physics.control import joint_torque_magnitude
from neuromotor.physics.discrete import step_feedforward, step_rhs
from neuromotor.physics.dynamics import Reference, active_mask
from neuromotor.physics.system import dofs_to_per_joint, per_joint_to_dofs

# Contact in the capture, tuned on the shipped walk's stance phases (docs/residuals.md). The
# floor is the feet's lowest vertex over the whole clip, which a toe reaches once, in a pivot or
# a landing: a bearing sole sits 2-5 cm above it on the walk (99.9 % of its slow vertices below
# 8 cm), and 4-8 cm on the CMU jumps, whose floor drifts by 2 cm (95 % below 8 cm). A
# shuffling swing foot passes as low (the walk's swing clears 5-10 cm), so speed decides there:
# a bearing vertex moves by the foot's roll alone (below 0.3 m/s on the walk), a swinging one
# at 1-4 m/s.
CONTACT_HEIGHT = 0.08  # m above the floor
CONTACT_SPEED = 0.5  # m/s over the step
# The ground branch's candidates and friction (physics/contact/ground.py there).
PER_BODY = 8  # lowest vertices per body
MAX_CONTACTS = 16  # lowest of all bodies' candidates (both soles of the mass model's feet)
FRICTION = 0.8  # Coulomb mu of the ground
FRICTION_DIRECTIONS = 8  # edges of the friction pyramid (a regular polygon on the cone)
# The small weights of the least-squares problem (units: body weights; module docstring).
REGULARIZATION = 1e-8
SMOOTHING = 1e-7
FAR = 1.0e6  # m: the height of a padding vertex


class CaptureContacts(eqx.Module):
    """The contact candidates of every step k (from x_k): ``G = MAX_CONTACTS`` lowest vertices."""

    body: Int[Array, "S G"]
    vertex: Int[Array, "S G"]  # index within its body's polyhedron
    point: Float[Array, "S G 3"]  # world, at x_k
    height: Float[Array, "S G"]  # above the floor (m)
    speed: Float[Array, "S G"]  # m/s over the step
    active: Bool[Array, "S G"]  # touching: height and speed below the thresholds


def body_vertices(shapes: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """Each body's polyhedron vertices (body frame, from the joint origin), padded: ``(B, V, 3)``
    and the valid mask ``(B, V)`` (a body without a shape has none)."""
    verts = [np.zeros((0, 3)) if s is None else np.asarray(s.vertices, np.float64).reshape(-1, 3) for s in shapes]
    n = max(1, max(len(v) for v in verts))
    padded, valid = np.zeros((len(verts), n, 3)), np.zeros((len(verts), n), bool)
    for b, v in enumerate(verts):
        padded[b, : len(v)], valid[b, : len(v)] = v, True
    return padded, valid


def vertex_world(model: Model, verts, pos, rot):
    """World vertices ``(..., B, V, 3)`` of bodies at COM positions ``pos`` and rotations ``rot``."""
    local = jnp.asarray(verts) - model.com[:, None, :]
    return pos[..., :, None, :] + jnp.einsum("...bij,bvj->...bvi", rot, local)


@functools.partial(compiler.jit, static_argnames=("per_body", "max_contacts"))
def capture_contacts(
    model: Model,
    verts,
    valid,
    pos: Float[Array, "S1 B 3"],
    rot: Float[Array, "S1 B 3 3"],
    floor,
    h,
    height=CONTACT_HEIGHT,
    speed=CONTACT_SPEED,
    per_body: int = PER_BODY,
    max_contacts: int = MAX_CONTACTS,
) -> CaptureContacts:
    """The touching vertices of every step of the grid (module docstring, item 1)."""
    world = vertex_world(model, verts, pos, rot)  # (S1, B, V, 3)
    gap = jnp.where(valid, world @ up_direction(model) - floor, FAR)[:-1]
    rate = jnp.linalg.norm(world[1:] - world[:-1], axis=-1) / h
    n_bodies, n_verts = valid.shape
    k = min(per_body, n_verts)
    idx = jnp.sort(jax.lax.top_k(-gap, k)[1], -1)  # (S, B, k): each body's lowest, by index
    take = lambda a: jnp.take_along_axis(a, idx, 2).reshape(a.shape[0], -1)
    slot_gap, slot_rate = take(gap), take(rate)
    slot_body = jnp.broadcast_to(jnp.repeat(jnp.arange(n_bodies), k), slot_gap.shape)
    keep = jax.lax.top_k(-slot_gap, min(max_contacts, slot_gap.shape[1]))[1]  # (S, G)
    pick = lambda a: jnp.take_along_axis(a, keep, 1)
    body, vertex = pick(slot_body), pick(idx.reshape(idx.shape[0], -1))
    point = world[:-1][jnp.arange(body.shape[0])[:, None], body, vertex]
    g, r = pick(slot_gap), pick(slot_rate)
    return CaptureContacts(body, vertex, point, g, r, (g < height) & (r < speed))


def com_positions(model: Model, pos: Float[Array, "... B 3"]) -> Float[Array, "... 3"]:
    """The whole body's centre of mass."""
    return jnp.einsum("b,...bi->...i", model.mass, pos) / jnp.sum(model.mass)


@functools.partial(compiler.jit, static_argnames=("cfg",))
def required_wrench(model: Model, cfg, pos, rot, velocity) -> tuple[Float[Array, "S 6"], Float[Array, "S 3"]]:
    """The wrench the driven root carries over each step of the discrete inverse, as force and
    moment about the whole body's COM at x_k (world), and that COM: ``(S, 6)``, ``(S, 3)``.
    ``velocity`` ``(S1, B, 6)``: the discrete inverse's u_k (``Reference.velocity``)."""
    rhs = jax.vmap(lambda r, a, b: step_rhs(model, cfg, r, a, b))(rot[:-1], velocity[:-1], velocity[1:])
    com = com_positions(model, pos[:-1])
    force = jnp.sum(rhs[..., :3], 1)
    moment = jnp.sum(rhs[..., 3:] + jnp.cross(pos[:-1] - com[:, None], rhs[..., :3]), 1)
    return jnp.concatenate([force, moment], -1), com


def root_wrench_about(model: Model, lam_root: Float[Array, "... 6"], pos, rot, point) -> Float[Array, "... 6"]:
    """The root rows' multipliers (force at the root joint's origin, moment) as a wrench about
    ``point`` (world): the root's ``J^T lam`` puts ``lam[:3]`` at the origin and ``lam[3:]``."""
    origin = pos[..., 0, :] + jnp.einsum("...ij,j->...i", rot[..., 0, :, :], -model.com[0])
    force = lam_root[..., :3]
    return jnp.concatenate([force, lam_root[..., 3:] + jnp.cross(origin - point, force)], -1)


def pyramid_edges(up, mu: float = FRICTION, sides: int = FRICTION_DIRECTIONS, references=()) -> np.ndarray:
    """``(..., sides, 3)``: the friction pyramid's edges ``up + mu d_j`` on the Coulomb cone, with
    ``d_j = cos(2 pi j / N) t1 + sin(2 pi j / N) t2`` (the ground LCP's polygon: t1 from
    ``references``, world ``(..., 3)`` each, a body's forward and left axes,
    :func:`facing_basis`; none: the world axes' tangents)."""
    up = np.asarray(up, np.float64)
    refs = [jnp.asarray(r, jnp.float64) for r in references] or [jnp.zeros(3)]
    normal = jnp.broadcast_to(jnp.asarray(up), np.broadcast_shapes(*(r.shape for r in refs)))
    t1, t2 = (np.asarray(t)[..., None, :] for t in facing_basis(normal, *refs))
    ang = 2.0 * np.pi * np.arange(sides) / sides
    return up + mu * (np.cos(ang)[:, None] * t1 + np.sin(ang)[:, None] * t2)


@dataclasses.dataclass(frozen=True)
class GroundReaction:
    """The ground reaction forces of every step and what they leave (N, N m; world)."""

    force: np.ndarray  # (S, G, 3) at the contact points (zero where not touching)
    produced: np.ndarray  # (S, 6) their wrench: force, moment about the COM
    residual: np.ndarray  # (S, 6) required - produced


def _wrench_matrix(points, com, edges, length):
    """(6, P * N): the wrench over (W, W L) of unit edge coefficients at each point (``edges``
    (P, N, 3): each point's pyramid)."""
    lever = (points - com)[:, None, :]
    moment = np.cross(lever, edges) / length
    return np.concatenate([edges, moment], -1).reshape(-1, 6).T


def solve_grf(
    required,
    contacts: CaptureContacts,
    com,
    up,
    weight: float,
    length: float,
    mu: float = FRICTION,
    sides: int = FRICTION_DIRECTIONS,
    regularization: float = REGULARIZATION,
    smoothing: float = SMOOTHING,
    axes=None,
) -> GroundReaction:
    """The ground reaction forces of every step (module docstring, item 3): one NNLS per step,
    in time order (each step leans on the previous one's forces at the same vertices);
    ``axes`` (S, G, 2, 3): the world forward and left axes of each candidate's body, which
    orient its pyramid (:func:`pyramid_edges`; None: the world axes)."""
    required, com = np.asarray(required, np.float64), np.asarray(com, np.float64)
    point, active = np.asarray(contacts.point), np.asarray(contacts.active)
    key = np.asarray(contacts.body) * (1 << 20) + np.asarray(contacts.vertex)
    refs = () if axes is None else (np.asarray(axes)[..., 0, :], np.asarray(axes)[..., 1, :])
    edges = np.broadcast_to(pyramid_edges(up, mu, sides, refs), point.shape[:2] + (sides, 3))  # (S, G, N, 3)
    scale = np.array([weight] * 3 + [weight * length] * 3)
    force = np.zeros(point.shape)
    previous: dict[int, np.ndarray] = {}
    for k in range(required.shape[0]):
        idx = np.flatnonzero(active[k])
        if idx.size == 0:
            previous = {}
            continue
        a = _wrench_matrix(point[k, idx], com[k], edges[k, idx], length)
        prior = np.concatenate([previous.get(int(key[k, i]), np.zeros(sides)) for i in idx])
        # REGULARIZATION |c|^2 + SMOOTHING |c - prior|^2 = damping |c - target|^2 + a constant
        damping = regularization + smoothing
        lhs = np.concatenate([a, np.sqrt(damping) * np.eye(a.shape[1])])
        rhs = np.concatenate([required[k] / scale, np.sqrt(damping) * (smoothing / damping) * prior])
        coef = nnls(lhs, rhs, maxiter=50 * a.shape[1])[0].reshape(-1, sides)
        force[k, idx] = weight * np.einsum("pn,pnd->pd", coef, edges[k, idx])
        previous = {int(key[k, i]): coef[j] for j, i in enumerate(idx)}
    produced = point_wrench(force, point, com[:, None])
    return GroundReaction(force, produced, required - produced)


def point_wrench(force, point, about) -> np.ndarray:
    """``(..., 6)``: forces ``(..., P, 3)`` at points ``(..., P, 3)`` as one wrench about ``about``
    ``(..., 1, 3)``: their sum and their moment."""
    force = np.asarray(force)
    moment = np.cross(np.asarray(point) - np.asarray(about), force)
    return np.concatenate([force.sum(-2), moment.sum(-2)], -1)


def body_wrenches(model: Model, contacts: CaptureContacts, force, pos) -> np.ndarray:
    """``(S, B, 6)``: the ground reaction forces as each body's external force and torque about
    its COM at x_k (world), the ``external`` of :func:`contact_feedforward`."""
    pos = np.asarray(pos)[: force.shape[0]]
    body = np.asarray(contacts.body)
    out = np.zeros((force.shape[0], model.n_bodies, 6))
    steps = np.arange(force.shape[0])[:, None].repeat(body.shape[1], 1)
    lever = np.asarray(contacts.point) - pos[steps, body]
    np.add.at(out, (steps, body), np.concatenate([force, np.cross(lever, force)], -1))
    return out


@functools.partial(compiler.jit, static_argnames=("cfg",))
def contact_feedforward(model: Model, cfg, ref: Reference, quat, external):
    """The discrete inverse of the reference's steps with known external forces on the bodies
    (``external`` ``(S, B, 6)``: force, torque about the COM, world, as :func:`body_wrenches`
    gives the ground reaction forces): ``(tau (S, n), lam (S, nc), relative residual (S,))``.
    ``quat`` ``(S1, B, 4)``: the capture's body rotations on the grid. The root's rows ``lam[:, :6]``
    then carry only what the external forces leave (about the root joint's origin); ``tau`` is
    the joints' feedforward of a body held up by them (a free root): replace the reference's
    with :func:`with_feedforward`. ``cfg``: the step options the reference was made with (the
    root's rows are part of the solve either way; ``free_root`` is not read)."""
    if ref.velocity is None:
        raise ValueError("contact_feedforward needs the discrete inverse's velocities (Reference.velocity)")
    active = dofs_to_per_joint(model, active_mask(model, cfg.driven, quat.dtype))
    u = ref.velocity
    return jax.vmap(
        lambda la, q, a, b, e: step_feedforward(model, cfg, la, active, None, q, a, b, e),
    )(ref.local_axes[:-1], quat[:-1], u[:-1], u[1:], external)


def with_feedforward(model: Model, ref: Reference, tau: Float[Array, "S n"]) -> Reference:
    """The reference with the feedforward ``tau`` of its S steps (the last repeated on the grid's
    end, as the reference does) and the joints' |T_j| that the controller scales by."""
    tau = jnp.concatenate([tau, tau[-1:]], 0)
    axes = per_joint_to_dofs(model, jnp.moveaxis(jnp.swapaxes(ref.local_axes, -1, -2), 0, 2))
    activation = joint_torque_magnitude(model, jnp.moveaxis(axes, 0, 1), tau)
    return eqx.tree_at(lambda r: (r.tau, r.activation), ref, (tau, activation))
