"""The contact step: the ordinary step of Eq. 2 plus its contact rows (Section 4): the ball's
contacts and the bodies' contacts with the ground, one LCP.

Contact sources
    Two sources of candidates, each choosing its nearest candidates per step: the ball (against
    every capsule and, ``ContactSettings.ground``, the ground; ``ContactSettings.max_contacts``
    kept) and the ground (the bodies' lowest polyhedron vertices against the plane,
    :mod:`neuromotor.physics.contact.ground`; ``Ground.max_contacts`` kept). Either may be
    absent. Candidates are numbered the ball's first, then the ground's slots; the contacts of a
    step are the ball's kept candidates, then the ground's.

Contact frame and Jacobian
    A contact has a + side and a - side: the ball and a body (or the ground) for the ball's
    candidates, a body (at its vertex) and the ground for the ground's. With unit normal n
    pointing from the - side to the + side, tangents t1, t2 and contact points p_+ and p_-, the
    relative velocity of the + side with respect to the - side along d is

        d . (v_+ + w_+ x (p_+ - x_+)) - d . (v_- + w_- x (p_- - x_-)) = Jc_i,d  v,

    so Jc has rows ``[d, (p_+ - x_+) x d]`` on the + side's body (the ball: p_+ - x_+ = -r n) and
    ``-[d, (p_- - x_-) x d]`` on the - side's (none for the ground). The contact impulse
    P_i = (lam_n, f_t1, f_t2) acts as +Jc^T P: equal and opposite on the two sides (linear
    momentum is conserved exactly).

Free velocity and responses
    The ordinary step's stages (:func:`neuromotor.physics.dynamics.equations_of_motion`) build
    Eq. 2 for the chosen solver (``StepOptions.solver``: dense, tree or null-space). The solver
    gives the free velocity v_f (no contact) and, with one factorization for every contact row,
    the responses X = A^-1 [Jc^T; 0] to unit contact impulses
    (:meth:`~neuromotor.physics.solvers.KKTSolver.contact_responses`); the ball's block
    diag(m I, 2/5 m r^2 I) (when there is a ball) is inverted in closed form. So the Delassus
    matrix is W = Jc X and v+ = v_f + X P. The null-space solvers keep X in joint space,
    X = S H^-1 (Jc S)^T with the rows ``Jc S`` in closed form and ``W = (Jc S) H^-1 (Jc S)^T``,
    and map to the bodies only the three impulse sums a step needs (X P, X (1 - s) P and the
    position projection's X mu). The LCP ``w = W P + Jc v_f - target e_n`` is solved
    by :mod:`neuromotor.physics.contact.lcp`.

Time of impact and restitution
    A candidate is active when it would close within the step, ``g <= h max(-u_f, 0)``, or is
    already touching, g <= margin (0; ``Ground.margin`` when the bodies have a ground), with g
    the gap at the step start and u_f = (Jc v_f)_n. The impact happens at the fraction
    s = g / (h (-u_f)) of the step (0 when touching). A contact touching within the margin at
    g > 0 may close its gap within the step and no more: its target below is lowered by g / h.
    Newton's law with restitution e (the ball's for its contacts, the ground's for the bodies')
    acts on the normal velocity at the impact, u_s = u + s (u_f - u) (u the pre-step normal
    velocity), when it approaches faster than ``restitution_threshold``:

        target = max(0, -e u_s + (1 - s)(u_f - u))     (bounce; 0 otherwise: resting contact)

    (the second term is the free acceleration over the rest of the step). Positions move with
    v_f up to the impact and with v+ after it: the generalized displacement of the step is
    ``h v_f + h X ((1 - s) * P)``; so a ball (or a dropped body) bounces off the surface itself, not from where the
    step began, and the map from launch speed to trajectory stays continuous when the impact
    moves from one step to the next. Remaining penetration of the linearized end gap
    ``g_end = g + h u_f + h (W ((1 - s) * P))_n`` is removed by a position-level projection in
    the spirit of Cline & Pai's post-stabilization (mu >= 0, g_end + W_nn mu >= 0,
    complementary; displacement X_n mu), then the joint constraints are post-stabilized as in
    the contact-free step.

A moving ground (a platform)
    A base motion (``ForcePulses.base_velocity``/``base_offset``) under a free root moves the
    ground instead of the root (:class:`GroundMotion`): over the step from t_k the plane is at
    ``height + up . D_k`` and moves with V_k+1 (the base motion's own position update,
    D_k+1 = D_k + h V_k+1). The ground's contacts then see the body's velocity relative to the
    plane, ``Jc v - d . V``, in the ranking of the slots, the activity, the restitution target
    and the LCP, so friction drags the feet along. A tilt (``ForcePulses.base_turn``/``base_spin``
    /``base_pivot``) turns the plane as well: over the step from t_k its normal is ``n_k = R_k up``,
    it passes through the pivot's moved image, and a point x of it moves with
    ``V_k+1 + Omega_k+1 x (x - c_k)`` (c_k = pivot + D_k); the contacts take n_k as their normal
    and that point velocity at their vertex as the ground's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from neuromotor.model.skeleton import Model
from neuromotor.physics import solvers
from neuromotor.physics.balance import Posture
from neuromotor.physics.contact.ball import Ball, BallState, initial_ball_state
from neuromotor.physics.contact.detection import (
    ContactSettings,
    candidate_bodies,
    candidate_names,
    detect,
    facing_basis,
    single_gap,
    up_direction,
)
from neuromotor.physics.contact.ground import Ground, friction_references, ground_normal, ground_slots, vertex_gap
from neuromotor.physics.contact.lcp import lcp_residual, solve_gap_projection, solve_lcp_pgs
from neuromotor.physics.contact.shapes import Capsules
from neuromotor.physics.dynamics import Eq2, Params, SimModel, StepInfo, badness, equations_of_motion, hold, integrate
from neuromotor.physics.reflex import History
from neuromotor.physics.system import State
from neuromotor.rotations import quat_rotate, quat_turn

_TINY = 1e-12


class ContactScene(eqx.Module):
    """What the contact step adds to the character: the ball and the bodies' capsules (or None,
    None: no ball), the settings, and the ground under the bodies (None: the bodies touch
    nothing)."""

    ball: Ball | None
    capsules: Capsules | None
    settings: ContactSettings = eqx.field(static=True)
    ground: Ground | None = None

    @property
    def n_ball_candidates(self) -> int:
        if self.ball is None:
            return 0
        assert self.capsules is not None, "a ball needs the bodies' capsules"
        return self.capsules.radius.shape[0] + int(self.settings.ground)

    @property
    def n_candidates(self) -> int:
        return self.n_ball_candidates + (0 if self.ground is None else self.ground.n_slots)


def scene_candidate_bodies(scene: ContactScene) -> Int[Array, " C"]:
    """The character's body of every candidate (-1 for the ball against the ground): the ball's
    candidates, then the ground's slots."""
    parts = []
    if scene.ball is not None:
        assert scene.capsules is not None
        parts.append(candidate_bodies(scene.capsules, scene.settings))
    if scene.ground is not None:
        parts.append(scene.ground.slot_body)
    return jnp.concatenate(parts) if parts else jnp.zeros((0,), jnp.int32)


def scene_candidate_names(model: Model, scene: ContactScene) -> tuple[str, ...]:
    """Names of the candidates: the ball's (capsule names, ``ground``), then ``BODY@ground[r]``."""
    names: tuple[str, ...] = ()
    if scene.ball is not None:
        assert scene.capsules is not None
        names = candidate_names(scene.capsules, scene.settings)
    if scene.ground is not None:
        per = scene.ground.per_body
        names += tuple(f"{b}@ground[{r}]" for b in model.body_names for r in range(per))
    return names


def scene_gaps(model: Model, scene: ContactScene, ball_pos, pos, rot) -> Float[Array, " C"]:
    """Every candidate's gap (the ball's, then the ground's slots) at one configuration."""
    parts = []
    if scene.ball is not None:
        assert scene.capsules is not None
        parts.append(detect(model, scene.capsules, scene.settings, scene.ball.radius, ball_pos, pos, rot)[0])
    if scene.ground is not None:
        parts.append(ground_slots(model, scene.ground, pos, rot).gap)
    return jnp.concatenate(parts) if len(parts) > 1 else parts[0]


class GroundMotion(eqx.Module):
    """The ground's motion over one step (a platform: a base motion under a free root, and its
    tilt, if any)."""

    offset: Float[Array, ""]  # up . D_k: how far the plane has risen at the step start (m)
    vel: Float[Array, " 3"]  # V_k+1: its velocity over the step (world, m/s)
    vel_pre: Float[Array, " 3"]  # V_k: its velocity at the step start
    # A tilt (None: the plane keeps its normal): n_k = R_k up, the pivot's place c_k = pivot + D_k,
    # the plane's height along n_k, Omega_k+1 and Omega_k (world, rad/s).
    normal: Float[Array, " 3"] | None = None
    pivot: Float[Array, " 3"] | None = None
    height: Float[Array, ""] | None = None
    spin: Float[Array, " 3"] | None = None
    spin_pre: Float[Array, " 3"] | None = None

    def point_velocity(self, x: Float[Array, "K 3"], before: bool = False) -> Float[Array, "K 3"]:
        """The plane's velocity at world points ``x`` over the step (``before``: at its start)."""
        vel, spin = (self.vel_pre, self.spin_pre) if before else (self.vel, self.spin)
        if spin is None:
            return jnp.broadcast_to(vel, x.shape)
        assert self.pivot is not None
        return vel + jnp.cross(spin, x - self.pivot)

    def relative_twist(self, pos: Float[Array, "B 3"], v6: Float[Array, "B 6"]) -> Float[Array, "B 6"]:
        """Bodies' twists ([linear at the COM, angular]) relative to the plane's motion."""
        ang = v6[:, 3:] if self.spin is None else v6[:, 3:] - self.spin
        return jnp.concatenate([v6[:, :3] - self.point_velocity(pos), ang], -1)


def ground_motion(sim: SimModel, params: Params, scene: ContactScene, k) -> GroundMotion | None:
    """The ground's motion in step k: the base motion's (and tilt's) when the root is free and
    there is a ground, else None (a still ground: the step's program is the one without a base
    motion)."""
    pulses = params.pulses
    if scene.ground is None or not sim.options.free_root or pulses.base_velocity is None:
        return None
    assert pulses.base_offset is not None
    up = up_direction(sim.model)
    motion = GroundMotion(pulses.base_offset[k] @ up, pulses.base_velocity[k + 1], pulses.base_velocity[k])
    if pulses.base_turn is None:
        return motion
    assert pulses.base_spin is not None and pulses.base_pivot is not None
    normal = quat_rotate(pulses.base_turn[k], up)
    lift = pulses.base_pivot @ up - scene.ground.height  # the pivot's height above the level plane
    centre = pulses.pivot_at(k)
    return dataclasses.replace(
        motion,
        normal=normal,
        pivot=centre,
        height=centre @ normal - lift,
        spin=pulses.base_spin[k + 1],
        spin_pre=pulses.base_spin[k],
    )


def _moved(scene: ContactScene, gm: GroundMotion | None) -> ContactScene:
    """The scene with its ground where it is at the step start (``gm`` None: unchanged)."""
    if gm is None or scene.ground is None:
        return scene
    if gm.normal is None:
        ground = dataclasses.replace(scene.ground, height=scene.ground.height + gm.offset)
    else:
        assert gm.height is not None
        ground = dataclasses.replace(scene.ground, height=gm.height, normal=gm.normal)
    return dataclasses.replace(scene, ground=ground)


class ContactInfo(eqx.Module):
    """Per-candidate contact record of one step (the ball's candidates: capsules, then the
    ground; then the ground's slots)."""

    impulse: Float[Array, "C 3"]  # on the + side (the ball; the body on the ground), world (N s)
    normal_impulse: Float[Array, " C"]  # lam_n (N s)
    slack: Float[Array, " C"]  # w_n = post normal velocity minus target (m/s)
    target: Float[Array, " C"]  # normal velocity target (restitution)
    gap: Float[Array, " C"]  # gap at the step start (m)
    gap_impact: Float[Array, " C"]  # gap at the impact instant t + s h (m)
    toi: Float[Array, " C"]  # impact fraction s of the step
    active: Bool[Array, " C"]
    residual: Float[Array, " C"]  # the LCP's residual at the impulses (m/s, lcp.lcp_residual)

    @property
    def step_residual(self) -> Float[Array, ...]:
        """The largest LCP residual of each step (m/s; over the last axis, the candidates)."""
        return jnp.max(self.residual, -1)

    @property
    def touching(self) -> Bool[Array, ...]:
        """Whether each step had an active contact (over the last axis, the candidates)."""
        return jnp.any(self.active, -1)

    @classmethod
    def before_any_step(cls, gap: Float[Array, " C"]) -> ContactInfo:
        """The record at t_0: no impulse, the gaps of the initial configuration."""
        zero = jnp.zeros_like(gap)
        return cls(
            jnp.zeros(gap.shape + (3,), gap.dtype), zero, zero, zero, gap, gap, zero, jnp.zeros(gap.shape, bool), zero
        )


class ContactData(eqx.Module):
    """What the contact step advances: the ordinary step's :class:`~neuromotor.physics.dynamics.Data`
    (``k``, ``state``, ``info``) plus the ball, the impulses (the next step's warm start) and
    the contact record."""

    k: Int[Array, ""]
    state: State
    info: StepInfo
    ball: BallState | None  # None: no ball
    warm: Float[Array, "C 3"]
    contact: ContactInfo
    history: History | None = None  # the reflex's error history (neuromotor.physics.reflex)
    posture: Posture | None = None  # the balance loop's carry (neuromotor.physics.balance)

    def badness(self, max_speed: float) -> Float[Array, " B1"]:
        """The ordinary score per body, the ball last; the ball may legitimately fly faster than
        any limb, so it is judged against 5x the limit."""
        if self.ball is None:
            return badness(self.state, max_speed)
        ball = jax.tree_util.tree_map(
            lambda x: x[None], State(self.ball.pos, self.ball.quat, self.ball.vel, self.ball.omega)
        )
        return jnp.concatenate([badness(self.state, max_speed), badness(ball, 5.0 * max_speed)])

    def held(self, last: ContactData, bad) -> ContactData:
        """Itself, or after a blow-up (``bad``) with ``last``'s character and ball."""
        state, ball = hold((last.state, last.ball), (self.state, self.ball), bad)
        return dataclasses.replace(self, state=state, ball=ball)


def initial_contact_data(model: Model, scene: ContactScene, data) -> ContactData:
    """The ordinary initial data plus the ball at rest at its launch position."""
    ball = scene.ball
    ball_pos = None if ball is None else ball.position
    gap = scene_gaps(model, scene, ball_pos, data.state.pos, data.state.rot)
    warm = jnp.zeros(gap.shape + (3,), gap.dtype)
    bstate = None if ball is None else initial_ball_state(ball)
    return ContactData(
        data.k, data.state, data.info, bstate, warm, ContactInfo.before_any_step(gap), data.history, data.posture
    )


# ----------------------------------------------------------------------------- stages


class BallFree(eqx.Module):
    """The ball without contact over one step: frozen before launch, then free flight."""

    flying: Bool[Array, ""]
    vel: Float[Array, " 3"]  # at the step start (the launch velocity on the launch step)
    vel_free: Float[Array, " 3"]  # at the step end without contact
    omega: Float[Array, " 3"]

    @property
    def v(self) -> Float[Array, " 6"]:
        return jnp.concatenate([self.vel, self.omega])

    @property
    def v_free(self) -> Float[Array, " 6"]:
        return jnp.concatenate([self.vel_free, self.omega])


def ball_free_motion(model: Model, ball: Ball, h: float, t, k, bstate: BallState) -> BallFree:
    """The ball's contact-free motion over the step from t = t_k."""
    flying = t >= ball.launch - 1e-9
    # The launch velocity enters at the first flying step (a leaf: d/d speed flows through it).
    first = flying & ((k == 0) | (t - h < ball.launch - 1e-9))
    vel = jnp.where(first, ball.velocity, bstate.vel)
    return BallFree(flying, vel, jnp.where(flying, vel + h * model.gravity, vel), bstate.omega)


class ContactFrame(eqx.Module):
    """The contacts of a step (the ball's nearest candidates, then the ground's) and their rows
    of Jc (n, t1, t2 per contact)."""

    sel: Int[Array, " K"]  # candidate index of each contact
    gap_all: Float[Array, " C"]  # every candidate's gap at the step start
    dirs: Float[Array, "K 3 3"]  # (n, t1, t2) of each contact, world
    body: Int[Array, " K"]  # the contact's body (0 for the ball on the ground, whose rows are zero)
    jc_char: Float[Array, "3K 6B"]
    jc_ball: Float[Array, "3K 6"]  # (3K, 0) without a ball
    vertex: Int[Array, " Kg"]  # the ground contacts' vertices (within their bodies)
    point: Float[Array, "Kg 3"]  # the ground contacts' vertices (world, at the step start)
    n_ball: int = eqx.field(static=True)  # the first n_ball contacts are the ball's

    @property
    def gap(self) -> Float[Array, " K"]:
        return self.gap_all[self.sel]


def _ball_frame(model: Model, scene: ContactScene, state: State, bstate: BallState):
    """The ball's part of the frame: its ``max_contacts`` nearest candidates (capsules and the
    ground) and their rows; the ball is the + side."""
    n, dtype, settings = model.n_bodies, state.pos.dtype, scene.settings
    assert scene.ball is not None and scene.capsules is not None
    cand_body = candidate_bodies(scene.capsules, settings)
    n_keep = min(settings.max_contacts, cand_body.shape[0])
    gap_all, nrm_all, pt_all = detect(
        model, scene.capsules, settings, scene.ball.radius, bstate.pos, state.pos, state.rot
    )
    _, sel = jax.lax.top_k(-gap_all, n_keep)
    body, nrm = cand_body[sel], nrm_all[sel]
    # t1 up the body's surface; on a level one (the ground, the top of the head) along the flight.
    t1, t2 = facing_basis(nrm, up_direction(model), scene.ball.direction)
    dirs = jnp.stack([nrm, t1, t2], 1)  # (K, 3 dirs, 3)
    r_ball = -scene.ball.radius * nrm  # ball surface point minus centre
    bcol = jnp.concatenate([dirs, jnp.cross(r_ball[:, None, :], dirs)], -1)  # (K, 3, 6)
    on_body = (body >= 0).astype(dtype)
    bidx = jnp.maximum(body, 0)
    lever = pt_all[sel] - state.pos[bidx]
    ccol = -jnp.concatenate([dirs, jnp.cross(lever[:, None, :], dirs)], -1) * on_body[:, None, None]
    onehot = jax.nn.one_hot(bidx, n, dtype=dtype) * on_body[:, None]
    jc_char = jnp.einsum("kb,kdj->kdbj", onehot, ccol).reshape(3 * n_keep, 6 * n)
    return sel, gap_all, dirs, bidx, jc_char, bcol.reshape(3 * n_keep, 6)


def _ground_frame(model: Model, ground: Ground, state: State, v_free, h: float, ball_columns: int):
    """The ground's part of the frame: its ``max_contacts`` nearest slots (by the gap the step
    would leave without contact, ``g + h min(u_f, 0)``; :mod:`~neuromotor.physics.contact.ground`)
    and their rows; the body (at its vertex) is the + side, the ground the - side, the normal is up."""
    n, dtype = model.n_bodies, state.pos.dtype
    slots = ground_slots(model, ground, state.pos, state.rot, v_free.reshape(n, 6), h)
    n_keep = min(ground.max_contacts, ground.n_slots)
    _, sel = jax.lax.top_k(-slots.reach, n_keep)
    body = ground.slot_body[sel]
    nrm = jnp.broadcast_to(ground_normal(model, ground), (n_keep, 3))
    t1, t2 = facing_basis(nrm, *friction_references(ground, body, state.rot))
    dirs = jnp.stack([nrm, t1, t2], 1)
    lever = slots.point[sel] - state.pos[body]
    col = jnp.concatenate([dirs, jnp.cross(lever[:, None, :], dirs)], -1)  # (K, 3, 6)
    onehot = jax.nn.one_hot(body, n, dtype=dtype)
    jc_char = jnp.einsum("kb,kdj->kdbj", onehot, col).reshape(3 * n_keep, 6 * n)
    jc_ball = jnp.zeros((3 * n_keep, ball_columns), dtype)
    return sel, slots.gap, dirs, body, jc_char, jc_ball, slots.vertex[sel], slots.point[sel]


def contact_frame(
    model: Model, scene: ContactScene, state: State, bstate: BallState | None, v_free, h: float
) -> ContactFrame:
    """Detect, keep each source's nearest candidates and build their Jacobian rows (``v_free``:
    the character's contact-free velocity of the step, which ranks the ground's candidates)."""
    parts, vertex, point = [], jnp.zeros((0,), jnp.int32), jnp.zeros((0, 3), state.pos.dtype)
    if scene.ball is not None:
        assert bstate is not None
        parts.append(_ball_frame(model, scene, state, bstate))
    n_ball = parts[0][0].shape[0] if parts else 0
    if scene.ground is not None:
        *part, vertex, point = _ground_frame(model, scene.ground, state, v_free, h, 0 if scene.ball is None else 6)
        part[0] = part[0] + scene.n_ball_candidates  # the ground's slots follow the ball's candidates
        parts.append(tuple(part))
    if not parts:
        raise ValueError("a contact scene needs a ball or a ground")
    sel, gap_all, dirs, body, jc_char, jc_ball = (
        parts[0] if len(parts) == 1 else tuple(jnp.concatenate(xs) for xs in zip(*parts))
    )
    return ContactFrame(sel, gap_all, dirs, body, jc_char, jc_ball, vertex, point, n_ball)


class Responses(eqx.Module):
    """Free velocities and responses to unit contact impulses; contact-space velocities."""

    v_free: Float[Array, " 6B"]  # the character without contact
    x_char: Float[Array, "D 3K"]  # A^-1 [Jc^T; 0], the character's part, in the solver's coordinates (KKTSolver.lift)
    x_ball: Float[Array, "6 3K"]  # the ball's inverse mass times its Jc^T ((0, 3K) without a ball)
    w_mat: Float[Array, "3K 3K"]  # Delassus matrix Jc X
    u_free: Float[Array, "K 3"]  # contact velocities (n, t1, t2) without contact impulses
    u_pre: Float[Array, " K"]  # normal velocities at the step start
    lam: Float[Array, " nc"]  # constraint impulses of the free solve
    residual: Float[Array, ""]  # relative residual of the free solve of Eq. 2


class FreeSolve(eqx.Module):
    """The character's step without contact: Eq. 2 solved by the chosen solver."""

    v_free: Float[Array, "B 6"]
    lam: Float[Array, " nc"]  # constraint impulses
    residual: Float[Array, ""]  # relative residual of Eq. 2


def free_solve(solver: solvers.KKTSolver, eq: Eq2) -> FreeSolve:
    """The chosen solver's contact-free velocity and multipliers of Eq. 2."""
    v_free, aux = solver.solve(eq.system, eq.r, eq.b)
    lam, residual = solver.multipliers(eq.system, eq.r, eq.b, v_free, aux)
    return FreeSolve(v_free, lam, residual)


def responses(
    solver: solvers.KKTSolver,
    eq: Eq2,
    fs: FreeSolve,
    frame: ContactFrame,
    ball: Ball | None,
    free: BallFree | None,
    v: Float[Array, " 6B"],
) -> Responses:
    """The free velocity (``fs``), and the chosen solver's responses to unit contact impulses
    (:meth:`~neuromotor.physics.solvers.KKTSolver.contact_responses`: one factorization for
    every contact row)."""
    v_free, lam, residual = fs.v_free, fs.lam, fs.residual
    n6 = frame.jc_char.shape[1]
    k = frame.body.shape[0]
    rows = frame.jc_char.reshape(k, 3, n6 // 6, 6)[jnp.arange(k), :, frame.body]  # (K, 3, 6): each row's body
    cr = solver.contact_responses(eq.system, n6 // 6, frame.body, rows, eq.b)
    v_free, x_char, w_char = v_free.reshape(n6), cr.x, cr.w
    if ball is None:
        x_ball = jnp.zeros((0, x_char.shape[1]), x_char.dtype)
        w_mat = w_char
        u_free = (frame.jc_char @ v_free).reshape(-1, 3)
        u_pre = (frame.jc_char @ v).reshape(-1, 3)[:, 0]
        return Responses(v_free, x_char, x_ball, w_mat, u_free, u_pre, lam, residual)
    assert free is not None
    x_ball = ball.inverse_mass[:, None] * frame.jc_ball.T
    w_mat = w_char + frame.jc_ball @ x_ball
    u_free = (frame.jc_char @ v_free + frame.jc_ball @ free.v_free).reshape(-1, 3)
    u_pre = (frame.jc_char @ v + frame.jc_ball @ free.v).reshape(-1, 3)[:, 0]
    return Responses(v_free, x_char, x_ball, w_mat, u_free, u_pre, lam, residual)


def relative_to_ground(frame: ContactFrame, resp: Responses, gm: GroundMotion | None) -> Responses:
    """The ground's contacts' velocities relative to a moving ground, ``Jc v - d . V_g`` with V_g
    the plane's velocity at the contact (``gm`` None: unchanged)."""
    if gm is None:
        return resp
    nb = frame.n_ball
    dirs = frame.dirs[nb:]
    u_free = resp.u_free.at[nb:].add(-jnp.einsum("kdj,kj->kd", dirs, gm.point_velocity(frame.point)))
    u_pre = resp.u_pre.at[nb:].add(-jnp.einsum("kj,kj->k", dirs[:, 0], gm.point_velocity(frame.point, True)))
    return dataclasses.replace(resp, u_free=u_free, u_pre=u_pre)


class Impact(eqx.Module):
    """Which contacts act in the step, when, and with which normal velocity target."""

    active: Bool[Array, " K"]
    toi: Float[Array, " K"]  # impact fraction s of the step
    target: Float[Array, " K"]  # normal velocity target (restitution)
    q: Float[Array, " 3K"]  # LCP offset: w = W P + q


def per_contact(frame: ContactFrame, scene: ContactScene, ball_value, ground_value):
    """A (K,) array: ``ball_value`` for the ball's contacts, ``ground_value`` for the ground's."""
    k = frame.sel.shape[0]
    if scene.ground is None:
        return jnp.broadcast_to(ball_value, (k,))
    if scene.ball is None:
        return jnp.broadcast_to(ground_value, (k,))
    ball_value, ground_value = jnp.asarray(ball_value), jnp.asarray(ground_value)
    return jnp.concatenate(
        [jnp.broadcast_to(ball_value, (frame.n_ball,)), jnp.broadcast_to(ground_value, (k - frame.n_ball,))]
    )


def _ground_attr(scene: ContactScene, name: str):
    return None if scene.ground is None else getattr(scene.ground, name)


def _ball_attr(scene: ContactScene, name: str):
    return None if scene.ball is None else getattr(scene.ball, name)


def impact(frame: ContactFrame, resp: Responses, scene: ContactScene, h: float, flying) -> Impact:
    """Activity, time of impact and Newton's restitution target (see the module docstring).
    ``flying``: whether the ball has been launched (its contacts act only then)."""
    settings = scene.settings
    gap, uf_n, u_pre = frame.gap, resp.u_free[:, 0], resp.u_pre
    live = per_contact(frame, scene, flying, True)
    restitution = per_contact(frame, scene, _ball_attr(scene, "restitution"), _ground_attr(scene, "restitution"))
    reach = h * jnp.maximum(-uf_n, 0.0)
    margin = 0.0 if scene.ground is None else scene.ground.margin  # touching within it (with a ground)
    active = live & ((gap <= margin) | (gap <= reach))
    toi = jnp.where(active & (gap > margin), jnp.clip(gap / jnp.maximum(reach, _TINY), 0.0, 1.0), 0.0)
    u_s = u_pre + toi * (uf_n - u_pre)
    bounce = -u_s > settings.restitution_threshold
    target = jnp.where(bounce, jnp.maximum(0.0, -restitution * u_s + (1.0 - toi) * (uf_n - u_pre)), 0.0)
    # Touching within the margin: it may still close its gap in this step, and no more.
    target = target - jnp.where((gap > 0.0) & (gap <= margin), gap / h, 0.0)
    target = jnp.where(active, target, 0.0)
    q = (resp.u_free - jnp.stack([target, jnp.zeros_like(target), jnp.zeros_like(target)], -1)).reshape(-1)
    return Impact(active, toi, target, q)


def _when_touching(active, solve, zeros):
    """``solve()`` when a contact is active, else zeros (a select under vmap, where both run)."""
    return jax.lax.cond(jnp.any(active), solve, lambda: zeros)


def contact_impulses(frame: ContactFrame, resp: Responses, imp: Impact, scene: ContactScene, warm):
    """The LCP by PGS, warm started: impulses (K, 3), the normal slack w_n (K,) and the LCP's
    residual (K,) in m/s. Each contact has its source's friction (the ball's, or the ground's)."""
    settings = scene.settings
    mu = per_contact(frame, scene, _ball_attr(scene, "friction"), _ground_attr(scene, "friction"))
    p = _when_touching(
        imp.active,
        lambda: solve_lcp_pgs(
            resp.w_mat, imp.q, mu, imp.active, warm, settings.friction_directions, settings.pgs_iterations
        ),
        jnp.zeros_like(warm),
    )
    slack = (resp.w_mat @ p.reshape(-1) + imp.q).reshape(-1, 3)[:, 0]
    residual = lcp_residual(resp.w_mat, imp.q, mu, imp.active, p, settings.friction_directions)
    return p, slack, residual


class Motion(eqx.Module):
    """Velocities after the impulses and displacements of the step (generalized, 6 per body)."""

    v_char: Float[Array, " 6B"]
    v_ball: Float[Array, " 6"] | None
    d_char: Float[Array, " 6B"]
    d_ball: Float[Array, " 6"] | None


def motion(
    frame: ContactFrame,
    resp: Responses,
    imp: Impact,
    p,
    free: BallFree | None,
    settings: ContactSettings,
    h: float,
    lift: Callable[[Float[Array, "D R"]], Float[Array, "6B R"]],
) -> Motion:
    """v+ = v_f + X P; displacement with the impact inside the step, then the projection of the
    remaining linearized penetration (``lift``: the solver's map from its coordinates of
    ``resp.x_char`` to the bodies' velocities, :meth:`~neuromotor.physics.solvers.KKTSolver.lift`)."""
    flat = p.reshape(-1)
    late = (p * (1.0 - imp.toi)[:, None]).reshape(-1)
    sel_n = jnp.arange(frame.sel.shape[0]) * 3
    g_end = frame.gap + h * resp.u_free[:, 0] + h * (resp.w_mat @ late)[sel_n]
    w_nn = resp.w_mat[sel_n][:, sel_n]
    mu_pos = _when_touching(
        imp.active,
        lambda: solve_gap_projection(w_nn, g_end, imp.active, settings.position_iterations),
        jnp.zeros_like(g_end),
    )
    push = jnp.zeros(flat.shape[0], flat.dtype).at[sel_n].set(mu_pos)
    moved = lift(resp.x_char @ jnp.stack([late, push, flat], 1))  # (6B, 3): X late, X push, X P
    disp = h * (resp.v_free + moved[:, 0]) + moved[:, 1]
    v_char = resp.v_free + moved[:, 2]
    if free is None:
        return Motion(v_char, None, disp, None)
    disp_b = h * (free.v_free + resp.x_ball @ late)
    disp_b = jnp.where(free.flying, disp_b + resp.x_ball @ push, 0.0)
    return Motion(v_char, free.v_free + resp.x_ball @ flat, disp, disp_b)


def ball_after(bstate: BallState, free: BallFree, mo: Motion) -> BallState:
    """The ball at the step end; one that is not flying keeps its velocity and spin."""
    assert mo.d_ball is not None and mo.v_ball is not None
    return BallState(
        bstate.pos + mo.d_ball[:3],
        quat_turn(bstate.quat, mo.d_ball[3:]),
        jnp.where(free.flying, mo.v_ball[:3], free.vel),
        jnp.where(free.flying, mo.v_ball[3:], free.omega),
    )


def _gaps_at_impact(model: Model, scene: ContactScene, h: float, data: ContactData, free, frame, resp, imp, gm=None):
    """Each contact's gap at its impact instant, from the configuration moved by s h v_free (and
    a moving ground by s h V)."""
    state, vf6 = data.state, resp.v_free.reshape(model.n_bodies, 6)
    sh, bidx = imp.toi * h, frame.body
    pb = state.pos[bidx] + sh[:, None] * vf6[bidx, :3]
    qb = quat_turn(state.quat[bidx], sh[:, None] * vf6[bidx, 3:])
    parts = []
    nb = frame.n_ball
    if scene.ball is not None:
        assert free is not None and scene.capsules is not None and data.ball is not None
        caps, settings, radius = scene.capsules, scene.settings, scene.ball.radius
        cb = data.ball.pos + sh[:nb, None] * jnp.where(free.flying, free.vel_free, 0.0)
        parts.append(
            jax.vmap(lambda i, p_, q_, c_: single_gap(model, caps, settings, radius, i, p_, q_, c_))(
                frame.sel[:nb], pb[:nb], qb[:nb], cb
            )
        )
    if scene.ground is not None:
        ground = scene.ground
        gaps = jax.vmap(lambda b, v, p_, q_: vertex_gap(model, ground, b, v, p_, q_))(
            bidx[nb:], frame.vertex, pb[nb:], qb[nb:]
        )
        if gm is not None:
            gaps = gaps - sh[nb:] * jnp.einsum("kj,j->k", gm.point_velocity(frame.point), ground_normal(model, ground))
        parts.append(gaps)
    return jnp.concatenate(parts) if len(parts) > 1 else parts[0]


def contact_info(
    model: Model,
    scene: ContactScene,
    h: float,
    data: ContactData,
    free: BallFree | None,
    frame: ContactFrame,
    resp: Responses,
    imp: Impact,
    p,
    slack,
    residual,
    gm: GroundMotion | None = None,
) -> ContactInfo:
    """The step's record over all candidates, with the gap at the impact instant from the
    configuration moved by s h v_free (``gm``: the ground's motion, None: still)."""
    gap_imp = _gaps_at_impact(model, scene, h, data, free, frame, resp, imp, gm)
    scatter = lambda x, fill: jnp.full(frame.gap_all.shape + x.shape[1:], fill, x.dtype).at[frame.sel].set(x)
    return ContactInfo(
        impulse=scatter(jnp.einsum("kd,kdj->kj", p, frame.dirs), 0.0),
        normal_impulse=scatter(p[:, 0], 0.0),
        slack=scatter(jnp.where(imp.active, slack, 0.0), 0.0),
        target=scatter(imp.target, 0.0),
        gap=frame.gap_all,
        gap_impact=frame.gap_all.at[frame.sel].set(gap_imp),
        toi=scatter(imp.toi, 0.0),
        active=scatter(imp.active, False),
        residual=scatter(residual, 0.0),
    )


# ----------------------------------------------------------------------------- the step


def contact_step(sim: SimModel, params: Params, scene: ContactScene, data: ContactData) -> ContactData:
    """One step of Eq. 2 with its contacts (the ball's and the ground's): the ordinary step's
    stages, the contact rows added to the chosen solver's system (see the module docstring).
    ``info.lam`` holds the constraint forces of the contact-free solve."""
    model, h, k, state = sim.model, sim.options.h, data.k, data.state
    solver = solvers.get(sim.options.solver)
    eq = equations_of_motion(sim, params, data, solver)  # type: ignore[arg-type]  # ContactData has Data's fields
    free = None
    if scene.ball is not None:
        assert data.ball is not None
        free = ball_free_motion(model, scene.ball, h, sim.ref.time[k], k, data.ball)
    fs = free_solve(solver, eq)
    gm = ground_motion(sim, params, scene, k)
    scene = _moved(scene, gm)
    # The slots rank by the vertices' velocities relative to the ground.
    rank = fs.v_free if gm is None else gm.relative_twist(state.pos, fs.v_free.reshape(-1, 6)).reshape(fs.v_free.shape)
    frame = contact_frame(model, scene, state, data.ball, rank, h)
    resp = relative_to_ground(frame, responses(solver, eq, fs, frame, scene.ball, free, state.v), gm)
    imp = impact(frame, resp, scene, h, True if free is None else free.flying)
    p, slack, residual = contact_impulses(frame, resp, imp, scene, data.warm[frame.sel])
    mo = motion(frame, resp, imp, p, free, scene.settings, h, lambda x: solver.lift(eq.system, x))
    n = model.n_bodies
    new, violation = integrate(sim, solver, k, state, mo.d_char.reshape(n, 6), mo.v_char.reshape(n, 6), params.pulses)
    record = contact_info(model, scene, h, data, free, frame, resp, imp, p, slack, residual, gm)
    ball = None
    if free is not None:
        assert data.ball is not None
        ball = ball_after(data.ball, free, mo)
    return ContactData(
        k + 1,
        new,
        StepInfo(resp.residual, violation, eq.force, eq.points, resp.lam / h, eq.reflex),
        ball,
        jnp.zeros_like(data.warm).at[frame.sel].set(p),
        record,
        eq.history,
        eq.posture,
    )
