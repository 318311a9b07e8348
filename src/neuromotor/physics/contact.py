"""A flying ball hitting the character: contact as a linear complementarity problem (LCP).

Section 4 of the paper handles contact as an LCP at the velocity level, together with the joint
constraints (Cline 2002). This module adds one free rigid ball (solid sphere, radius r, mass m,
inertia 2/5 m r^2) to the linearly implicit step of Eq. 2 and solves its contacts with the
character's bodies and with the ground plane in the same step.

Collision shapes
    Every body is covered by **capsules fitted to its polyhedron**: one capsule per bone that
    the mass model wrapped with a prism, axis = the bone (joint origin to child joint or End
    Site, body frame), radius = the largest distance from that bone of the hull vertices nearest
    to it (the prism's circumradius; the capsule contains the prism and adds round end caps).
    A body without a counted bone (a padded cube) gets a sphere around its vertices. The ground
    is the plane ``up . x = ground_height`` with ``up = -gravity / |gravity|``. The character
    does not touch the ground (the root is driven along the mocap, as in the paper).

Contact frame and Jacobian
    For a candidate i (a capsule of body b, or the ground) with unit normal n pointing from the
    body to the ball, tangents t1, t2, body surface point p_b and ball surface point
    p_s = c - r n, the relative velocity of the ball with respect to the body along d is

        d . (v_s + w_s x (p_s - c)) - d . (v_b + w_b x (p_b - x_b)) = Jc_i,d  v,

    so Jc has rows ``[d, (p_s - c) x d]`` on the ball and ``-[d, (p_b - x_b) x d]`` on body b.
    The contact impulse P_i = (lam_n, f_t1, f_t2) acts on the ball as +Jc^T P, on the body as
    its negative part of Jc^T P (equal and opposite: linear momentum is conserved exactly).

Velocity-level LCP
    Let A be the constrained system of Eq. 2 (``[[M - hD - h^2 K, -J^T], [J, 0]]``) plus the
    ball's block diag(m I, 2/5 m r^2 I). One LU of A solves the free velocity v_f (no contact)
    and the responses X = A^-1 [Jc^T; 0] to unit contact impulses (multi right-hand side), so
    the Delassus matrix is W = Jc X and the post-contact velocity is v+ = v_f + X P. With
    w = W P + Jc v_f - target e_n the LCP per active contact reads

        lam_n >= 0,  w_n >= 0,  lam_n w_n = 0                       (non-penetration)
        f_t in mu lam_n Poly_N,   <w_t, f' - f_t> >= 0 for all f' in mu lam_n Poly_N

    where Poly_N is the regular N-gon with vertices d_j = (cos 2 pi j/N, sin 2 pi j/N): the
    friction pyramid of the Stewart-Trinkle LCP (f_t = sum_j beta_j d_j, beta_j >= 0, slack
    gamma = max_j(-d_j . w_t) >= 0 with sum_j beta_j <= mu lam_n complementary to gamma). The
    variational form above is its maximal-dissipation statement, which is what projected
    Gauss-Seidel (PGS) converges to: per contact, lam_n <- max(0, lam_n - w_n / W_nn), then
    f_t <- Proj(f_t - w_t / lambda_max(W_tt)) onto the scaled polygon (exact Euclidean
    projection). Fixed sweep count (``lax.fori_loop``), warm started from the previous step:
    jittable, vmappable and differentiable almost everywhere.

Time of impact and restitution
    A candidate is active when it would close within the step, ``g <= h max(-u_f, 0)`` (or is
    already touching, g <= 0), with g the gap at the step start and u_f = (Jc v_f)_n. The impact
    happens at the fraction s = g / (h (-u_f)) of the step (0 when touching). Newton's law with
    restitution e acts on the normal velocity at the impact, u_s = u + s (u_f - u) (u the
    pre-step normal velocity), when it approaches faster than ``restitution_threshold``:

        target = max(0, -e u_s + (1 - s)(u_f - u))     (bounce; 0 otherwise: resting contact)

    (the second term is the free acceleration over the rest of the step). Positions move with
    v_f up to the impact and with v+ after it: the generalized displacement of the step is
    ``h v_f + h X ((1 - s) * P)``; so a ball bounces off the surface itself, not from where the
    step began, and the map from launch speed to trajectory stays continuous when the impact
    moves from one step to the next. Remaining penetration of the linearized end gap
    ``g_end = g + h u_f + h (W ((1 - s) * P))_n`` is removed by a position-level projection in
    the spirit of Cline & Pai's post-stabilization (mu >= 0, g_end + W_nn mu >= 0,
    complementary; displacement X_n mu), then the joint constraints are post-stabilized as in
    the contact-free step.

Outputs (per step, per candidate): the impulse on the ball (world, N s; the force is impulse/h),
the normal impulse, the LCP slack w_n, the gap at the step start and at the impact instant, the
impact fraction s and the activity mask.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from neuromotor import compiler
from neuromotor.physics import dynamics as _dyn
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import (
    Reference,
    Rollout,
    SimConfig,
    SimulationDiverged,
    constraint_velocity,
    full_constraints,
    muscle_and_gyro,
    observe,
    post_stabilize,
    stiff_jacobians,
)
from neuromotor.physics.perturbation import ForcePulses, generalized_forces, no_pulses
from neuromotor.rotations import quat_to_matrix, quat_turn
from neuromotor.model.skeleton import Character, Model
from neuromotor.physics.system import State, gravity_forces, mass_matrix

_TINY = 1e-12


class Ball(eqx.Module):
    """The flying ball: every parameter is an array leaf (jit/vmap/grad over speed, mass, ...).

    Before ``launch`` (clip time) the ball hangs at ``position`` at rest (no gravity, no
    contact); the first step with t >= launch starts it at ``speed * direction``, then it flies
    under gravity.
    """

    radius: Float[Array, ""]  # m
    mass: Float[Array, ""]  # kg
    position: Float[Array, " 3"]  # centre at launch (world, m)
    direction: Float[Array, " 3"]  # unit launch direction (world)
    speed: Float[Array, ""]  # m/s
    restitution: Float[Array, ""]  # Newton's coefficient e in [0, 1]
    friction: Float[Array, ""]  # Coulomb coefficient mu
    launch: Float[Array, ""]  # s, clip time

    @property
    def velocity(self) -> Float[Array, " 3"]:
        return self.speed * self.direction

    @property
    def inertia(self) -> Float[Array, ""]:
        """Moment of inertia of a solid sphere about its centre, 2/5 m r^2."""
        return 0.4 * self.mass * self.radius**2


def make_ball(radius=0.11, mass=0.45, position=(0.0, 1.0, 0.0), velocity=None, speed=None,
              direction=None, restitution=0.6, friction=0.5, launch=0.0) -> Ball:
    """Build a :class:`Ball` from either ``velocity`` or ``speed`` and ``direction``."""
    if velocity is not None:
        velocity = np.asarray(velocity, np.float64)
        speed = float(np.linalg.norm(velocity))
        direction = velocity / speed if speed > 0 else np.array([1.0, 0.0, 0.0])
    else:
        direction = np.asarray(direction if direction is not None else (1.0, 0.0, 0.0), np.float64)
        norm = float(np.linalg.norm(direction))
        if not norm > 0:
            raise ValueError(f"ball direction must be non-zero, got {direction}")
        direction = direction / norm
        speed = 0.0 if speed is None else float(speed)
    f = lambda x: jnp.asarray(x, jnp.float64)
    return Ball(f(radius), f(mass), f(position), f(direction), f(speed), f(restitution), f(friction), f(launch))


class Capsules(eqx.Module):
    """Collision capsules fitted to the bodies (body frame, relative to the joint origin)."""

    body: Int[Array, " K"]
    a: Float[Array, "K 3"]
    b: Float[Array, "K 3"]
    radius: Float[Array, " K"]
    names: tuple[str, ...] = eqx.field(static=True)


class ContactSettings(eqx.Module):
    """Static settings of the contact solver."""

    friction_directions: int = eqx.field(static=True, default=8)  # N of the friction pyramid (>= 4)
    max_contacts: int = eqx.field(static=True, default=4)  # candidates kept per step (nearest)
    pgs_iterations: int = eqx.field(static=True, default=40)
    position_iterations: int = eqx.field(static=True, default=10)
    restitution_threshold: float = eqx.field(static=True, default=0.25)  # m/s
    ground: bool = eqx.field(static=True, default=True)
    ground_height: float = eqx.field(static=True, default=0.0)


class BallState(eqx.Module):
    pos: Float[Array, " 3"]
    quat: Float[Array, " 4"]
    vel: Float[Array, " 3"]
    omega: Float[Array, " 3"]


class ContactInfo(eqx.Module):
    """Per-candidate contact record of one step (capsules, then the ground)."""

    impulse: Float[Array, "C 3"]  # on the ball, world (N s); the body receives the opposite
    normal_impulse: Float[Array, " C"]  # lam_n (N s)
    slack: Float[Array, " C"]  # w_n = post normal velocity minus target (m/s)
    target: Float[Array, " C"]  # normal velocity target (restitution)
    gap: Float[Array, " C"]  # gap at the step start (m)
    gap_impact: Float[Array, " C"]  # gap at the impact instant t + s h (m)
    toi: Float[Array, " C"]  # impact fraction s of the step
    active: Bool[Array, " C"]


class ContactRollout(eqx.Module):
    """The character's :class:`Rollout` plus the ball and the contact record (leading S+1)."""

    run: Rollout
    ball: BallState
    contact: ContactInfo  # row 0 is all zeros (no step yet)


# ----------------------------------------------------------------------------- shapes


MIN_CAPSULE_BONE = 0.03  # m: shorter bones get no capsule of their own


def fit_capsules(character: Character) -> Capsules:
    """Capsules fitted to each body's polyhedron: one per bone of the body (to a child joint or
    End Site, at least ``MIN_CAPSULE_BONE`` long), radius the largest distance of the vertices
    nearest that bone; a body without such a bone (a hand, foot or skull whose End Site has zero
    length) gets one capsule along its shape's principal axis."""
    model = character.model
    offsets = np.asarray(model.joint_offset)
    ends = {k: np.asarray(model.end_site_offset[i]) for i, k in enumerate(model.end_site_joint)}
    body, aa, bb, rr, names = [], [], [], [], []
    for b, k in enumerate(model.body_joint):
        bones = [offsets[c] for c, p in enumerate(model.joint_parent) if p == k]
        if k in ends:
            bones.append(ends[k])
        bones = [e for e in bones if np.linalg.norm(e) >= MIN_CAPSULE_BONE]
        verts = np.asarray(character.shapes[b].vertices, np.float64)
        if not bones:
            a, e, r = _principal_capsule(verts)
            body.append(b), aa.append(a), bb.append(e), rr.append(r), names.append(model.body_names[b])
            continue
        dist = np.stack([_segment_distance_np(verts, np.zeros(3), e) for e in bones], 1)
        nearest = np.argmin(dist, 1)
        for i, e in enumerate(bones):
            mine = dist[nearest == i, i]
            r = float(mine.max()) if mine.size else float(dist[:, i].min())
            body.append(b), aa.append(np.zeros(3)), bb.append(np.asarray(e, np.float64)), rr.append(r)
            names.append(f"{model.body_names[b]}[{i}]" if len(bones) > 1 else model.body_names[b])
    return Capsules(jnp.asarray(body, jnp.int32), jnp.asarray(np.stack(aa)), jnp.asarray(np.stack(bb)),
                    jnp.asarray(rr), tuple(names))


def _principal_capsule(verts):
    """(a, b, radius) of a capsule along the principal axis of a vertex cloud that covers every
    vertex: radius the largest distance from the axis, end points at the extremes along it."""
    centre = verts.mean(0)
    _, _, vt = np.linalg.svd(verts - centre, full_matrices=False)
    axis = vt[0]
    t = (verts - centre) @ axis
    r = float(np.linalg.norm((verts - centre) - np.outer(t, axis), axis=1).max())
    return centre + float(t.min()) * axis, centre + float(t.max()) * axis, r


def _segment_distance_np(points, a, b):
    seg = b - a
    t = np.clip((points - a) @ seg / max(seg @ seg, _TINY), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * seg), axis=1)


def candidate_bodies(caps: Capsules, settings: ContactSettings) -> Int[Array, " C"]:
    """Body of every contact candidate; -1 for the ground (static world)."""
    extra = jnp.array([-1], jnp.int32) if settings.ground else jnp.zeros((0,), jnp.int32)
    return jnp.concatenate([caps.body, extra])


def candidate_names(caps: Capsules, settings: ContactSettings) -> tuple[str, ...]:
    return caps.names + (("ground",) if settings.ground else ())


def _safe_norm(x):
    sq = jnp.sum(x * x, -1)
    safe = jnp.where(sq > 0, sq, 1.0)
    return jnp.where(sq > 0, jnp.sqrt(safe), 0.0)


def _capsule_contact(a_w, b_w, rad, centre, ball_r):
    """Sphere against a world capsule: gap, normal (capsule to ball), point on the capsule."""
    seg = b_w - a_w
    t = jnp.clip(jnp.dot(centre - a_w, seg) / jnp.maximum(jnp.dot(seg, seg), _TINY), 0.0, 1.0)
    q = a_w + t * seg
    d = centre - q
    dist = _safe_norm(d)
    # Ball centre on the axis (never in practice): any normal will do.
    n = jnp.where(dist > _TINY, d / jnp.maximum(dist, _TINY), jnp.array([0.0, 1.0, 0.0]))
    return dist - rad - ball_r, n, q + rad * n


def detect(model: Model, caps: Capsules, settings: ContactSettings, ball_radius, centre, pos, rot):
    """Gap (C,), unit normal (C,3) from body to ball, body surface point (C,3) per candidate."""
    bodies = caps.body
    to_world = lambda p: pos[bodies] + jnp.einsum("kij,kj->ki", rot[bodies], p - model.com[bodies])
    gap, n, p = jax.vmap(_capsule_contact, (0, 0, 0, None, None))(
        to_world(caps.a), to_world(caps.b), caps.radius, centre, ball_radius)
    if settings.ground:
        up = _up(model)
        height = jnp.dot(centre, up) - settings.ground_height
        gap = jnp.concatenate([gap, (height - ball_radius)[None]])
        n = jnp.concatenate([n, up[None]])
        p = jnp.concatenate([p, (centre - height * up)[None]])
    return gap, n, p


def _up(model: Model) -> Float[Array, " 3"]:
    """-gravity / |gravity|; +y (the clips' up axis) in zero gravity."""
    norm = _safe_norm(model.gravity)
    return jnp.where(norm > 0, -model.gravity / jnp.maximum(norm, _TINY), jnp.array([0.0, 1.0, 0.0]))


def tangent_basis(n: Float[Array, "... 3"]) -> tuple[Float[Array, "... 3"], Float[Array, "... 3"]]:
    """Two unit tangents completing n to a right-handed frame (n, t1, t2)."""
    helper = jnp.where(jnp.abs(n[..., :1]) < 0.57, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 0.0, 1.0]))
    t1 = jnp.cross(n, helper)
    t1 = t1 / _safe_norm(t1)[..., None]
    return t1, jnp.cross(n, t1)


# ----------------------------------------------------------------------------- LCP solver


def project_polygon(p: Float[Array, " 2"], scale, sides: int) -> Float[Array, " 2"]:
    """Euclidean projection of p onto scale * Poly_N (regular N-gon, vertices (cos, sin)(2 pi j/N))."""
    ang = 2.0 * jnp.pi * jnp.arange(sides) / sides
    verts = scale * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
    normals = jnp.stack([jnp.cos(ang + jnp.pi / sides), jnp.sin(ang + jnp.pi / sides)], -1)
    inside = jnp.max(normals @ p) <= scale * math.cos(math.pi / sides)
    edge = jnp.roll(verts, -1, 0) - verts
    t = jnp.clip(jnp.sum((p - verts) * edge, -1) / jnp.maximum(jnp.sum(edge * edge, -1), _TINY), 0.0, 1.0)
    cand = verts + t[:, None] * edge
    best = cand[jnp.argmin(jnp.sum((cand - p) ** 2, -1))]
    return jnp.where(inside, p, best)


def solve_lcp_pgs(w_mat: Float[Array, "3K 3K"], q: Float[Array, " 3K"], mu, active: Bool[Array, " K"],
                  p0: Float[Array, "K 3"], sides: int, iterations: int) -> Float[Array, "K 3"]:
    """Projected Gauss-Seidel for the contact LCP (see the module docstring).

    w = W P + q, contacts ordered (n, t1, t2). Inactive contacts keep P = 0.
    """
    k = active.shape[0]
    mask = active.astype(w_mat.dtype)
    diag_n = jnp.array([w_mat[3 * i, 3 * i] for i in range(k)])
    inv_n = mask / jnp.maximum(diag_n, _TINY)
    # Step for the tangential update: 1 / largest eigenvalue of the 2x2 tangent block.
    tt = jnp.stack([w_mat[3 * i + 1:3 * i + 3, 3 * i + 1:3 * i + 3] for i in range(k)])
    tt = 0.5 * (tt + jnp.swapaxes(tt, -1, -2))
    tr, det = tt[:, 0, 0] + tt[:, 1, 1], tt[:, 0, 0] * tt[:, 1, 1] - tt[:, 0, 1] ** 2
    lam_max = 0.5 * tr + jnp.sqrt(jnp.maximum(0.25 * tr**2 - det, 0.0))
    step_t = 1.0 / jnp.maximum(lam_max, _TINY)

    def sweep(_, p):
        p = p.reshape(-1)
        for i in range(k):
            rows = w_mat[3 * i:3 * i + 3]
            w = rows @ p + q[3 * i:3 * i + 3]
            lam = jnp.maximum(0.0, p[3 * i] - w[0] * inv_n[i]) * mask[i]
            w_t = w[1:] + rows[1:, 3 * i] * (lam - p[3 * i])
            f_t = project_polygon(p[3 * i + 1:3 * i + 3] - step_t[i] * w_t, mu * lam, sides) * mask[i]
            p = p.at[3 * i].set(lam).at[3 * i + 1:3 * i + 3].set(f_t)
        return p.reshape(k, 3)

    return jax.lax.fori_loop(0, iterations, sweep, p0 * mask[:, None])


def solve_gap_projection(w_nn: Float[Array, "K K"], g: Float[Array, " K"], active, iterations: int):
    """mu >= 0, g + W_nn mu >= 0, mu (g + W_nn mu) = 0 by projected Gauss-Seidel (positions)."""
    k = g.shape[0]
    mask = active.astype(g.dtype)
    inv = mask / jnp.maximum(jnp.diag(w_nn), _TINY)

    def sweep(_, m):
        for i in range(k):
            m = m.at[i].set(jnp.maximum(0.0, m[i] - (w_nn[i] @ m + g[i]) * inv[i]))
        return m

    return jax.lax.fori_loop(0, iterations, sweep, jnp.zeros_like(g))


# ----------------------------------------------------------------------------- the step


def _active_mask(model: Model, driven, dtype):
    return jnp.array([0.0 if b in driven else 1.0 for b in model.dof_body], dtype)


def _angular_embed(mat, n: int):
    out = jnp.zeros((mat.shape[0], n, 6), mat.dtype)
    return out.at[:, :, 3:].set(mat.reshape(mat.shape[0], n, 3)).reshape(mat.shape[0], 6 * n)


def stiff_terms(model: Model, gains: Gains, ref_k, active, rot, omega, solver: str = "dense", targets=None):
    """k_stiff (6B,), K and D (6B, 6B) of the stiff torques, for the dense system of Eq. 2.

    ``solver="tree"`` or ``"nullspace"`` takes the exact tree-sparse angular blocks of ``dynamics.stiff_blocks``
    (per-joint Jacobians: far cheaper than a dense ``jacfwd``) and scatters them into the dense
    matrices; ``"dense"`` differentiates the whole force vector (``dynamics.stiff_jacobians``).
    Both give the same K and D (a test checks it). ``targets`` (``ref.joint_targets(k)``) spares
    the tree-sparse path rebuilding the joints' Euler axes and desired rotations."""
    n = model.n_bodies
    if solver in ("tree", "nullspace"):
        sb = _dyn.stiff_blocks(model, gains, ref_k, active, rot, omega, targets=targets)
        c = jnp.arange(1, n)
        p = jnp.array(model.body_parent[1:])
        b = jnp.arange(n)

        def dense(diag, up, down):
            out = jnp.zeros((n, 3, n, 3), rot.dtype).at[b, :, b, :].set(diag)
            out = out.at[c, :, p, :].add(up).at[p, :, c, :].add(down)
            return jnp.zeros((n, 6, n, 6), rot.dtype).at[:, 3:, :, 3:].set(out).reshape(6 * n, 6 * n)

        k_stiff = jnp.concatenate([jnp.zeros_like(sb.k), sb.k], -1).reshape(-1)
        return k_stiff, dense(sb.k_diag, sb.k_up, sb.k_down), dense(sb.d_diag, sb.d_up, sb.d_down)
    k_stiff, kmat, dmat = stiff_jacobians(model, gains, ref_k, active, rot, omega)
    return k_stiff, _angular_embed(kmat, n), _angular_embed(dmat, n)


def contact_step(model: Model, gains: Gains, pulses: ForcePulses, cfg: SimConfig, ref: Reference,
                 ball: Ball, caps: Capsules, settings: ContactSettings, k, state: State,
                 bstate: BallState, warm: Float[Array, "C 3"]):
    """One step of Eq. 2 with the ball and its contacts (see the module docstring)."""
    h = cfg.h
    n = model.n_bodies
    dtype = state.pos.dtype
    rot = state.rot
    t = ref.time[k]
    # -- the character's linearly implicit system, as in dynamics.step
    active_dofs = _active_mask(model, cfg.driven, dtype)
    ref_k = ref.controller_inputs(k)
    if cfg.implicit:
        k_stiff, kmat, dmat = stiff_terms(model, gains, ref_k, active_dofs, rot, state.omega,
                                          getattr(cfg, "solver", "dense"), ref.joint_targets(k))
    else:
        k_stiff = muscle_and_gyro(model, gains, ref_k, active_dofs, rot, state.omega)
        kmat = dmat = jnp.zeros((6 * n, 6 * n), dtype)
    f_pert, per_body, points = generalized_forces(pulses, t, n, state.pos, rot, model.com)
    kvec = k_stiff + gravity_forces(model) + f_pert
    m = mass_matrix(model, rot)
    jac = full_constraints(model, cfg.driven, rot, cfg.free_root)
    nc = jac.shape[0]
    v = state.v
    lhs = jnp.block([[m - h * dmat - h * h * kmat, -jac.T], [jac, jnp.zeros((nc, nc), dtype)]])
    b = constraint_velocity(model, cfg.driven, rot, ref.root_vel[k + 1], ref.root_omega[k + 1],
                            ref.rel_omega[k + 1], cfg.free_root)
    rhs = jnp.concatenate([m @ v + h * (kvec - dmat @ v), b])

    # -- the ball: frozen before launch, free flight under gravity after
    flying = t >= ball.launch - 1e-9
    # The launch velocity enters at the first flying step (a leaf: d/d speed flows through it).
    first = flying & ((k == 0) | (t - h < ball.launch - 1e-9))
    vb = jnp.where(first, ball.velocity, bstate.vel)
    vb_free = jnp.where(flying, vb + h * model.gravity, vb)
    wb = bstate.omega

    # -- candidates: keep the K nearest, build their Jacobian rows
    cand_body = candidate_bodies(caps, settings)
    n_cand = cand_body.shape[0]
    n_keep = min(settings.max_contacts, n_cand)
    gap_all, nrm_all, pt_all = detect(model, caps, settings, ball.radius, bstate.pos, state.pos, rot)
    _, sel = jax.lax.top_k(-gap_all, n_keep)
    body = cand_body[sel]
    gap, nrm, p_body = gap_all[sel], nrm_all[sel], pt_all[sel]
    t1, t2 = tangent_basis(nrm)
    dirs = jnp.stack([nrm, t1, t2], 1)  # (K, 3 dirs, 3)
    r_ball = -ball.radius * nrm  # ball surface point minus centre
    bcol = jnp.concatenate([dirs, jnp.cross(r_ball[:, None, :], dirs)], -1)  # (K, 3, 6)
    on_body = (body >= 0).astype(dtype)
    bidx = jnp.maximum(body, 0)
    lever = p_body - state.pos[bidx]
    ccol = -jnp.concatenate([dirs, jnp.cross(lever[:, None, :], dirs)], -1) * on_body[:, None, None]
    onehot = jax.nn.one_hot(bidx, n, dtype=dtype) * on_body[:, None]
    jc_char = jnp.einsum("kb,kdj->kdbj", onehot, ccol).reshape(3 * n_keep, 6 * n)
    jc_ball = bcol.reshape(3 * n_keep, 6)

    # -- one LU: free velocity and the response to unit contact impulses (multi-RHS)
    rhs_all = jnp.concatenate([rhs[:, None], jnp.concatenate([jc_char.T, jnp.zeros((nc, 3 * n_keep), dtype)])], 1)
    sol = jnp.linalg.solve(lhs, rhs_all)
    residual = jnp.linalg.norm(lhs @ sol[:, 0] - rhs) / jnp.maximum(jnp.linalg.norm(rhs), 1e-300)
    v_free = sol[:6 * n, 0]
    x_char = sol[:6 * n, 1:]  # (6B, 3K)
    inv_ball = jnp.concatenate([jnp.full(3, 1.0 / ball.mass), jnp.full(3, 1.0 / ball.inertia)])
    x_ball = inv_ball[:, None] * jc_ball.T  # (6, 3K)
    w_mat = jc_char @ x_char + jc_ball @ x_ball
    vb6_free = jnp.concatenate([vb_free, wb])
    u_free = (jc_char @ v_free + jc_ball @ vb6_free).reshape(n_keep, 3)
    u_pre = (jc_char @ v + jc_ball @ jnp.concatenate([vb, wb])).reshape(n_keep, 3)[:, 0]
    uf_n = u_free[:, 0]

    # -- activity, time of impact, restitution target
    reach = h * jnp.maximum(-uf_n, 0.0)
    active = flying & ((gap <= 0.0) | (gap <= reach))
    toi = jnp.where(active & (gap > 0.0), jnp.clip(gap / jnp.maximum(reach, _TINY), 0.0, 1.0), 0.0)
    u_s = u_pre + toi * (uf_n - u_pre)
    bounce = -u_s > settings.restitution_threshold
    target = jnp.where(bounce, jnp.maximum(0.0, -ball.restitution * u_s + (1.0 - toi) * (uf_n - u_pre)), 0.0)
    target = jnp.where(active, target, 0.0)
    q = (u_free - jnp.stack([target, jnp.zeros_like(target), jnp.zeros_like(target)], -1)).reshape(-1)

    p0 = warm[sel]
    # Skip the sweeps when nothing touches (a select under vmap, where both branches run).
    any_active = jnp.any(active)
    imp = jax.lax.cond(any_active, lambda: solve_lcp_pgs(w_mat, q, ball.friction, active, p0,
                                                         settings.friction_directions, settings.pgs_iterations),
                       lambda: jnp.zeros_like(p0))
    flat = imp.reshape(-1)
    slack = (w_mat @ flat + q).reshape(n_keep, 3)[:, 0]

    # -- velocities after the impulse; displacement with the impact inside the step
    v_new = v_free + x_char @ flat
    vb6_new = vb6_free + x_ball @ flat
    late = (imp * (1.0 - toi)[:, None]).reshape(-1)
    disp = h * (v_free + x_char @ late)
    disp_b = h * (vb6_free + x_ball @ late)
    # Position projection of the remaining (linearized) penetration.
    sel_n = jnp.arange(n_keep) * 3
    g_end = gap + h * uf_n + h * (w_mat @ late)[sel_n]
    w_nn = w_mat[sel_n][:, sel_n]
    mu_pos = jax.lax.cond(any_active, lambda: solve_gap_projection(w_nn, g_end, active, settings.position_iterations),
                          lambda: jnp.zeros_like(g_end))
    push = jnp.zeros(3 * n_keep, dtype).at[sel_n].set(mu_pos)
    disp = disp + x_char @ push
    disp_b = disp_b + x_ball @ push
    disp_b = jnp.where(flying, disp_b, 0.0)

    v_new = v_new.reshape(n, 6)
    d6 = disp.reshape(n, 6)
    pos = state.pos + d6[:, :3]
    quat = quat_turn(state.quat, d6[:, 3:])
    pos, quat, c = post_stabilize(model, cfg.driven, pos, quat, ref.stabilization_targets(k), cfg.stab_iters,
                                  cfg.free_root)
    new = State(pos, quat, v_new[:, :3], v_new[:, 3:])
    new_ball = BallState(bstate.pos + disp_b[:3], quat_turn(bstate.quat, disp_b[3:]),
                         jnp.where(flying, vb6_new[:3], vb), jnp.where(flying, vb6_new[3:], wb))

    # -- the gap at the impact instant, from the configuration moved by s h v_free
    vf6 = v_free.reshape(n, 6)
    sh = toi * h
    pb = state.pos[bidx] + sh[:, None] * vf6[bidx, :3]
    qb = quat_turn(state.quat[bidx], sh[:, None] * vf6[bidx, 3:])
    cb = bstate.pos + sh[:, None] * jnp.where(flying, vb_free, 0.0)
    gap_imp = jax.vmap(lambda i, p_, q_, c_: _single_gap(model, caps, settings, ball.radius, i, p_, q_, c_))(
        sel, pb, qb, cb)

    world = jnp.einsum("kd,kdj->kj", imp, dirs)
    scatter = lambda x, fill: jnp.full((n_cand,) + x.shape[1:], fill, x.dtype).at[sel].set(x)
    info = ContactInfo(
        impulse=scatter(world, 0.0),
        normal_impulse=scatter(imp[:, 0], 0.0),
        slack=scatter(jnp.where(active, slack, 0.0), 0.0),
        target=scatter(target, 0.0),
        gap=gap_all,
        gap_impact=gap_all.at[sel].set(gap_imp),
        toi=scatter(toi, 0.0),
        active=scatter(active, False),
    )
    warm_new = scatter(imp, 0.0)
    violation = jnp.max(jnp.abs(c)) if c.size else jnp.zeros((), dtype)
    return new, new_ball, warm_new, info, (residual, violation, per_body, points)


def _single_gap(model, caps, settings, ball_radius, i, pos_b, quat_b, centre):
    """Gap of candidate i with its body at (pos_b, quat_b) and the ball at centre."""
    n_caps = caps.radius.shape[0]
    if settings.ground:
        ground = jnp.dot(centre, _up(model)) - settings.ground_height - ball_radius
    else:
        ground = jnp.zeros((), centre.dtype)
    j = jnp.minimum(i, n_caps - 1)
    b = caps.body[j]
    rot = quat_to_matrix(quat_b)
    to_w = lambda p: pos_b + rot @ (p - model.com[b])
    g_cap, _, _ = _capsule_contact(to_w(caps.a[j]), to_w(caps.b[j]), caps.radius[j], centre, ball_radius)
    return jnp.where(i >= n_caps, ground, g_cap)


# ----------------------------------------------------------------------------- rollout


def initial_ball_state(ball: Ball) -> BallState:
    z = jnp.zeros(3, ball.position.dtype)
    return BallState(ball.position, jnp.array([1.0, 0.0, 0.0, 0.0], ball.position.dtype), z, z)


def _badness(state: State, bstate: BallState, max_speed: float):
    pos = jnp.concatenate([state.pos, bstate.pos[None]])
    quat = jnp.concatenate([state.quat, bstate.quat[None]])
    vel = jnp.concatenate([state.vel, bstate.vel[None]])
    omega = jnp.concatenate([state.omega, bstate.omega[None]])
    finite = (jnp.all(jnp.isfinite(pos), -1) & jnp.all(jnp.isfinite(quat), -1)
              & jnp.all(jnp.isfinite(vel), -1) & jnp.all(jnp.isfinite(omega), -1))
    speed = jnp.maximum(jnp.linalg.norm(vel, axis=-1), jnp.linalg.norm(omega, axis=-1))
    # The ball may legitimately fly faster than any limb: judge it against 5x the limit.
    limit = jnp.concatenate([jnp.full(state.pos.shape[0], max_speed), jnp.array([5.0 * max_speed])])
    return jnp.where(finite, speed / limit, jnp.inf)


def contact_rollout(model: Model, gains: Gains, pulses: ForcePulses | None, ref: Reference,
                    cfg: SimConfig, ball: Ball, caps: Capsules, settings: ContactSettings) -> ContactRollout:
    """``cfg.n_steps`` steps of :func:`contact_step` in one ``lax.scan``."""
    if ref.time.shape[0] < cfg.n_steps + 1:
        raise ValueError(f"reference has {ref.time.shape[0] - 1} steps, config asks for {cfg.n_steps}")
    if pulses is None:
        pulses = no_pulses()
    n_cand = candidate_bodies(caps, settings).shape[0]

    def body(carry, k):
        state, bstate, warm, bad_step, bad_body = carry
        new, new_ball, warm, info, (res, viol, force, points) = contact_step(
            model, gains, pulses, cfg, ref, ball, caps, settings, k, state, bstate, warm)
        score = _badness(new, new_ball, cfg.max_speed)
        first = (jnp.max(score) > 1.0) & (bad_step < 0)
        bad_step = jnp.where(first, k, bad_step)
        bad_body = jnp.where(first, jnp.argmax(score), bad_body)
        keep = lambda a, b: jnp.where(bad_step >= 0, a, b)
        new = jax.tree_util.tree_map(keep, state, new)
        new_ball = jax.tree_util.tree_map(keep, bstate, new_ball)
        theta, theta_dot = observe(model, new, ref, k + 1)
        out = (new, new_ball, theta, theta_dot, info, res, viol, force, points)
        return (new, new_ball, warm, bad_step, bad_body), out

    init, binit = ref.init, initial_ball_state(ball)
    dtype = init.pos.dtype
    carry0 = (init, binit, jnp.zeros((n_cand, 3), dtype), jnp.asarray(-1), jnp.asarray(-1))
    (_, _, _, bad_step, bad_body), outs = jax.lax.scan(body, carry0, jnp.arange(cfg.n_steps))
    states, bstates, theta, theta_dot, info, res, viol, force, points = outs
    theta0, theta_dot0 = observe(model, init, ref, 0)
    stack = lambda a, b: jnp.concatenate([a[None], b], 0)
    _, f0, p0 = generalized_forces(pulses, ref.time[0], model.n_bodies, init.pos, init.rot, model.com)
    info0 = jax.tree_util.tree_map(lambda x: jnp.zeros_like(x[0]), info)
    gap0 = detect(model, caps, settings, ball.radius, ball.position, init.pos, init.rot)[0]
    info0 = eqx.tree_at(lambda i: (i.gap, i.gap_impact), info0, (gap0, gap0))
    run = Rollout(
        ref.time[: cfg.n_steps + 1],
        jax.tree_util.tree_map(stack, init, states),
        stack(theta0, theta),
        stack(theta_dot0, theta_dot),
        res,
        viol,
        stack(f0, force),
        stack(p0, points),
        bad_step,
        bad_body,
    )
    return ContactRollout(run, jax.tree_util.tree_map(stack, binit, bstates),
                          jax.tree_util.tree_map(stack, info0, info))


def check_contact_rollout(model: Model, out: ContactRollout) -> ContactRollout:
    """Raise :class:`SimulationDiverged` naming the step and the body (or ``ball``)."""
    step_ = int(out.run.diverged_step)
    if step_ >= 0:
        b = int(out.run.diverged_body)
        name = model.body_names[b] if b < model.n_bodies else "ball"
        raise SimulationDiverged(step_, float(out.run.time[step_ + 1]), name)
    return out


contact_rollout_jit = compiler.jit(contact_rollout, static_argnames=("cfg", "settings"))


def never_launched(ball: Ball) -> Ball:
    """The same ball held at its start for ever: the unperturbed run with the same compiled code."""
    return eqx.tree_at(lambda b: b.launch, ball, jnp.full_like(ball.launch, jnp.inf))


@eqx.filter_jit
def _com_at(model: Model, traj, body, t):
    from neuromotor.model.kinematics import body_poses

    return body_poses(model, traj.q(t))[0][body]


def aim_ball(model: Model, traj, position, speed: float, target_body: int, launch: float,
             iterations: int = 20) -> np.ndarray:
    """Unit launch direction u so that the ballistic path from ``position`` at ``speed``,
    ``x(T) = position + speed u T + g T^2 / 2``, meets the target body's mocap COM at launch + T.

    The flight time solves ``|target(launch + T) - position - g T^2 / 2| = speed T`` by fixed-point
    iteration (a contraction for the throws of interest: target speed and g T << ball speed).
    Raises ValueError when it does not converge (a ball too slow to reach the target)."""
    position = np.asarray(position, np.float64)
    g = np.asarray(model.gravity)
    flight = previous = 0.0
    for _ in range(iterations):
        com = np.asarray(_com_at(model, traj, jnp.asarray(target_body), jnp.asarray(launch + flight, jnp.float64)))
        d = com - position - 0.5 * g * flight**2
        flight, previous = float(np.linalg.norm(d)) / speed, flight
        if not flight < 1e6:  # running away: out of reach
            break
    # A ball too slow to reach the target makes the iteration diverge (or crawl): refuse it
    # rather than aim at nothing (a miss of more than 1 mm along the path).
    if not (math.isfinite(flight) and speed * abs(flight - previous) <= 1e-3):
        raise ValueError(f"is too low: a ball at {speed:g} m/s cannot reach the target from {position.tolist()} "
                         f"(the aim does not converge)")
    return d / np.linalg.norm(d)


# ----------------------------------------------------------------------------- pipeline glue


class BallSetup(eqx.Module):
    """What :func:`neuromotor.studies.simulate.prepare` keeps for a ``[ball]`` config."""

    ball: Ball
    capsules: Capsules
    settings: ContactSettings = eqx.field(static=True)


def ball_setup(spec: dict, character: Character, traj, body_index, source: str = "config") -> BallSetup:
    """Build the ball from a parsed ``[ball]`` table (see :func:`neuromotor.config.parse_ball`)."""
    from neuromotor.config import ConfigError

    model = character.model
    try:
        ball = ball_from_spec(spec, model, traj, body_index)
    except ConfigError:
        raise
    except ValueError as e:
        raise ConfigError(f"{source}: field 'ball.speed' {e}") from None
    settings = ContactSettings(
        friction_directions=spec.get("friction_directions", 8), max_contacts=spec.get("max_contacts", 4),
        pgs_iterations=spec.get("pgs_iterations", 40),
        restitution_threshold=spec.get("restitution_threshold", 0.25), ground=spec.get("ground", True),
        ground_height=spec.get("ground_height", 0.0))
    return BallSetup(ball, fit_capsules(character), settings)


def ball_from_spec(spec: dict, model: Model, traj, body_index) -> Ball:
    """The :class:`Ball` of a parsed ``[ball]`` table; aims it when the table names a target.
    Raises ValueError when the aim is impossible (speed <= 0, or too slow to reach it)."""
    if "velocity" in spec:
        return make_ball(spec["radius"], spec["mass"], spec["position"], velocity=spec["velocity"],
                         restitution=spec["restitution"], friction=spec["friction"], launch=spec["launch"])
    direction = spec.get("direction")
    if "target" in spec:
        if not spec["speed"] > 0:
            raise ValueError("must be > 0 to aim at a target")
        direction = aim_ball(model, traj, spec["position"], spec["speed"], body_index(spec["target"]),
                             spec["launch"])
    return make_ball(spec["radius"], spec["mass"], spec["position"], speed=spec["speed"], direction=direction,
                     restitution=spec["restitution"], friction=spec["friction"], launch=spec["launch"])


def balls_at_speeds(setup, speeds) -> Ball:
    """The config's ball at each speed (leading axis = speed): exactly the ball that
    ``simulate.prepare`` builds for the config with ``ball.speed`` set to that speed. A ball
    aimed at a ``target`` is re-aimed per speed (a slower ball needs a higher arc); a
    ``direction`` or ``velocity`` keeps its direction. Raises ValueError for a speed that
    cannot reach the target."""
    from neuromotor.config import ConfigError
    from neuromotor.studies.simulate import body_lookup

    spec = dict(setup.config.ball)
    if "velocity" in spec:  # speed + direction of the given velocity
        spec["direction"] = np.asarray(setup.ball.ball.direction).tolist()
        del spec["velocity"]
    index = body_lookup(setup.model, setup.config.source)
    balls = []
    for s in speeds:
        try:
            balls.append(ball_from_spec(dict(spec, speed=float(s)), setup.model, setup.traj, index))
        except ConfigError:
            raise
        except ValueError as e:
            raise ValueError(f"speed {float(s):g} m/s {e}") from None
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *balls)


def run_ball(setup, check: bool = True):
    """Perturbed (ball flies) and unperturbed (ball never launched, pulses off) rollouts, with
    the same compiled function; returns :class:`neuromotor.studies.simulate.RunResult` with ``ball``."""
    from neuromotor.studies.simulate import RunResult, _zero, run_metrics

    bs = setup.ball
    model = setup.model
    pert = contact_rollout_jit(model, setup.gains, setup.pulses, setup.ref, setup.sim, bs.ball, bs.capsules, bs.settings)
    base = contact_rollout_jit(model, setup.gains, _zero(setup.pulses), setup.ref, setup.sim,
                               never_launched(bs.ball), bs.capsules, bs.settings)
    if check:
        check_contact_rollout(model, base)
        check_contact_rollout(model, pert)
    result = RunResult(pert.run, base.run, run_metrics(setup, pert.run, base.run))
    result.ball = pert
    c = pert.contact
    result.metrics["ball_peak_impulse_Ns"] = float(jnp.max(jnp.linalg.norm(c.impulse, axis=-1)))
    result.metrics["ball_first_contact_s"] = _first_contact(pert)
    return result


def _first_contact(out: ContactRollout) -> float | None:
    hit = np.nonzero(np.asarray(out.contact.normal_impulse).max(-1) > 0)[0]
    return float(out.run.time[hit[0]]) if hit.size else None


def ball_arrays(setup, result) -> dict[str, np.ndarray]:
    """The ball's part of RUN.npz: ``ball_pos`` (T,3), ``ball_quat``, ``ball_vel``,
    ``ball_radius``, per contact candidate ``contact_impulse`` / ``contact_force`` (T,C,3, on
    the ball, world; the body gets the opposite), ``contact_point`` (T,C,3, on the body),
    ``contact_normal_impulse``, ``contact_gap`` (T,C), ``contact_body`` (C, -1 = ground),
    ``contact_names`` (C)."""
    out: ContactRollout = result.ball
    bs: BallSetup = setup.ball
    c = out.contact
    impulse = np.asarray(c.impulse)
    ball_pos = np.asarray(out.ball.pos)
    model = setup.model
    gaps = np.asarray(c.gap)
    # Closest points on the bodies (and the ground) to the ball, for drawing the force arrows.
    points = np.asarray(jax.vmap(lambda p, q, centre: detect(model, bs.capsules, bs.settings, bs.ball.radius,
                                                             centre, p, quat_to_matrix(q))[2])(
        out.run.states.pos, out.run.states.quat, out.ball.pos))
    return {
        "ball_pos": ball_pos,
        "ball_quat": np.asarray(out.ball.quat),
        "ball_vel": np.asarray(out.ball.vel),
        "ball_radius": np.asarray(float(bs.ball.radius)),
        "contact_impulse": impulse,
        "contact_force": impulse / setup.sim.h,
        "contact_normal_impulse": np.asarray(c.normal_impulse),
        "contact_point": points,
        "contact_gap": gaps,
        "contact_body": np.asarray(candidate_bodies(bs.capsules, bs.settings)),
        "contact_names": np.array(candidate_names(bs.capsules, bs.settings)),
    }


def sweep_ball_speed(setup, speeds) -> dict[str, np.ndarray]:
    """Ball speed as the perturbation magnitude: one vmapped batch of contact rollouts.

    The batch holds one run per speed plus the unperturbed run (the ball never launched), so a
    single compiled function serves them all. Returns per speed the peak joint-angle deviation
    from the unperturbed run (RMS over DOFs, degrees), its time, and the peak contact impulse."""
    from neuromotor.studies import metrics as mx

    bs = setup.ball
    speeds = jnp.asarray(speeds, jnp.float64)
    balls = jax.vmap(lambda s: eqx.tree_at(lambda b: b.speed, bs.ball, s))(speeds)
    base = never_launched(bs.ball)
    balls = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), balls, base)
    batch = _batched_rollout(setup.model, setup.gains, setup.pulses, setup.ref, setup.sim, balls,
                             bs.capsules, bs.settings)
    theta = batch.run.theta
    dev = jax.vmap(lambda th: mx.deviation(th, theta[-1]))(theta[:-1])
    return {
        "speed": np.asarray(speeds),
        "peak_deviation_deg": np.asarray(jnp.max(dev, -1)),
        "time_of_peak_s": np.asarray(batch.run.time[0])[np.asarray(jnp.argmax(dev, -1))],
        "peak_impulse_Ns": np.asarray(jnp.max(jnp.linalg.norm(batch.contact.impulse[:-1], axis=-1), axis=(1, 2))),
    }


_batched_rollout = compiler.jit(jax.vmap(contact_rollout, in_axes=(None, None, None, None, None, 0, None, None)),
                           static_argnums=(4, 7))
