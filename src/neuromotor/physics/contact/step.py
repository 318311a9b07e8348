"""The contact step: the ordinary step of Eq. 2 plus the ball and its contact rows (Section 4).

Contact frame and Jacobian
    For a candidate i (a capsule of body b, or the ground) with unit normal n pointing from the
    body to the ball, tangents t1, t2, body surface point p_b and ball surface point
    p_s = c - r n, the relative velocity of the ball with respect to the body along d is

        d . (v_s + w_s x (p_s - c)) - d . (v_b + w_b x (p_b - x_b)) = Jc_i,d  v,

    so Jc has rows ``[d, (p_s - c) x d]`` on the ball and ``-[d, (p_b - x_b) x d]`` on body b.
    The contact impulse P_i = (lam_n, f_t1, f_t2) acts on the ball as +Jc^T P, on the body as
    its negative part of Jc^T P (equal and opposite: linear momentum is conserved exactly).

Free velocity and responses
    The ordinary step's stages (:func:`neuromotor.physics.dynamics.equations_of_motion`) build
    Eq. 2 for the chosen solver (``StepOptions.solver``: dense, tree or null-space). The solver
    gives the free velocity v_f (no contact) and, vmapped over the contact rows with one
    factorization, the responses X = A^-1 [Jc^T; 0] to unit contact impulses; the ball's block
    diag(m I, 2/5 m r^2 I) is inverted in closed form. So the Delassus matrix is W = Jc X and
    v+ = v_f + X P. The LCP ``w = W P + Jc v_f - target e_n`` is solved by
    :mod:`neuromotor.physics.contact.lcp`.

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
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from neuromotor.model.skeleton import Model
from neuromotor.physics import solvers
from neuromotor.physics.contact.ball import Ball, BallState, initial_ball_state
from neuromotor.physics.contact.detection import ContactSettings, candidate_bodies, detect, single_gap, tangent_basis
from neuromotor.physics.contact.lcp import solve_gap_projection, solve_lcp_pgs
from neuromotor.physics.contact.shapes import Capsules
from neuromotor.physics.dynamics import Eq2, Params, SimModel, StepInfo, badness, equations_of_motion, hold, integrate
from neuromotor.physics.reflex import History
from neuromotor.physics.system import State
from neuromotor.rotations import quat_turn

_TINY = 1e-12


class ContactScene(eqx.Module):
    """What the contact step adds to the character: the ball, the bodies' capsules, the settings."""

    ball: Ball
    capsules: Capsules
    settings: ContactSettings = eqx.field(static=True)


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

    @classmethod
    def before_any_step(cls, gap: Float[Array, " C"]) -> ContactInfo:
        """The record at t_0: no impulse, the gaps of the initial configuration."""
        zero = jnp.zeros_like(gap)
        return cls(jnp.zeros(gap.shape + (3,), gap.dtype), zero, zero, zero, gap, gap, zero, jnp.zeros(gap.shape, bool))


class ContactData(eqx.Module):
    """What the contact step advances: the ordinary step's :class:`~neuromotor.physics.dynamics.Data`
    (``k``, ``state``, ``info``) plus the ball, the impulses (the next step's warm start) and
    the contact record."""

    k: Int[Array, ""]
    state: State
    info: StepInfo
    ball: BallState
    warm: Float[Array, "C 3"]
    contact: ContactInfo
    history: History | None = None  # the reflex's error history (neuromotor.physics.reflex)

    def badness(self, max_speed: float) -> Float[Array, " B1"]:
        """The ordinary score per body, the ball last; the ball may legitimately fly faster than
        any limb, so it is judged against 5x the limit."""
        ball = jax.tree_util.tree_map(
            lambda x: x[None], State(self.ball.pos, self.ball.quat, self.ball.vel, self.ball.omega)
        )
        return jnp.concatenate([badness(self.state, max_speed), badness(ball, 5.0 * max_speed)])

    def held(self, last: ContactData, bad) -> ContactData:
        """Itself, or after a blow-up (``bad``) with ``last``'s character and ball."""
        kept = hold((last.state, last.ball), (self.state, self.ball), bad)
        return eqx.tree_at(lambda d: (d.state, d.ball), self, kept)


def initial_contact_data(model: Model, scene: ContactScene, data) -> ContactData:
    """The ordinary initial data plus the ball at rest at its launch position."""
    ball = scene.ball
    gap = detect(model, scene.capsules, scene.settings, ball.radius, ball.position, data.state.pos, data.state.rot)[0]
    warm = jnp.zeros(gap.shape + (3,), gap.dtype)
    return ContactData(
        data.k, data.state, data.info, initial_ball_state(ball), warm, ContactInfo.before_any_step(gap), data.history
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
    """The K nearest candidates of a step and their rows of Jc (n, t1, t2 per contact)."""

    sel: Int[Array, " K"]  # candidate index of each contact
    gap_all: Float[Array, " C"]  # every candidate's gap at the step start
    dirs: Float[Array, "K 3 3"]  # (n, t1, t2) of each contact, world
    body: Int[Array, " K"]  # the contact's body (0 for the ground, whose rows are zero)
    jc_char: Float[Array, "3K 6B"]
    jc_ball: Float[Array, "3K 6"]

    @property
    def gap(self) -> Float[Array, " K"]:
        return self.gap_all[self.sel]


def contact_frame(model: Model, scene: ContactScene, state: State, bstate: BallState) -> ContactFrame:
    """Detect, keep the ``max_contacts`` nearest candidates and build their Jacobian rows."""
    n, dtype, settings = model.n_bodies, state.pos.dtype, scene.settings
    cand_body = candidate_bodies(scene.capsules, settings)
    n_keep = min(settings.max_contacts, cand_body.shape[0])
    gap_all, nrm_all, pt_all = detect(
        model, scene.capsules, settings, scene.ball.radius, bstate.pos, state.pos, state.rot
    )
    _, sel = jax.lax.top_k(-gap_all, n_keep)
    body, nrm = cand_body[sel], nrm_all[sel]
    t1, t2 = tangent_basis(nrm)
    dirs = jnp.stack([nrm, t1, t2], 1)  # (K, 3 dirs, 3)
    r_ball = -scene.ball.radius * nrm  # ball surface point minus centre
    bcol = jnp.concatenate([dirs, jnp.cross(r_ball[:, None, :], dirs)], -1)  # (K, 3, 6)
    on_body = (body >= 0).astype(dtype)
    bidx = jnp.maximum(body, 0)
    lever = pt_all[sel] - state.pos[bidx]
    ccol = -jnp.concatenate([dirs, jnp.cross(lever[:, None, :], dirs)], -1) * on_body[:, None, None]
    onehot = jax.nn.one_hot(bidx, n, dtype=dtype) * on_body[:, None]
    jc_char = jnp.einsum("kb,kdj->kdbj", onehot, ccol).reshape(3 * n_keep, 6 * n)
    return ContactFrame(sel, gap_all, dirs, bidx, jc_char, bcol.reshape(3 * n_keep, 6))


class Responses(eqx.Module):
    """Free velocities and responses to unit contact impulses; contact-space velocities."""

    v_free: Float[Array, " 6B"]  # the character without contact
    x_char: Float[Array, "6B 3K"]  # A^-1 [Jc^T; 0], the character's part
    x_ball: Float[Array, "6 3K"]  # the ball's inverse mass times its Jc^T
    w_mat: Float[Array, "3K 3K"]  # Delassus matrix Jc X
    u_free: Float[Array, "K 3"]  # contact velocities (n, t1, t2) without contact impulses
    u_pre: Float[Array, " K"]  # normal velocities at the step start
    lam: Float[Array, " nc"]  # constraint impulses of the free solve
    residual: Float[Array, ""]  # relative residual of the free solve of Eq. 2


def responses(
    solver: solvers.KKTSolver, eq: Eq2, frame: ContactFrame, ball: Ball, free: BallFree, v: Float[Array, " 6B"]
) -> Responses:
    """The chosen solver's free velocity, and its responses to unit contact impulses (the
    contact rows as extra right-hand sides ``(Jc^T, 0)``, vmapped: one factorization)."""
    v_free, aux = solver.solve(eq.system, eq.r, eq.b)
    lam, residual = solver.multipliers(eq.system, eq.r, eq.b, v_free, aux)
    n6 = frame.jc_char.shape[1]
    x, _ = jax.vmap(lambda col: solver.solve(eq.system, col, jnp.zeros_like(eq.b)))(
        frame.jc_char.reshape(-1, n6 // 6, 6)
    )
    v_free, x_char = v_free.reshape(n6), x.reshape(-1, n6).T
    x_ball = ball.inverse_mass[:, None] * frame.jc_ball.T
    w_mat = frame.jc_char @ x_char + frame.jc_ball @ x_ball
    u_free = (frame.jc_char @ v_free + frame.jc_ball @ free.v_free).reshape(-1, 3)
    u_pre = (frame.jc_char @ v + frame.jc_ball @ free.v).reshape(-1, 3)[:, 0]
    return Responses(v_free, x_char, x_ball, w_mat, u_free, u_pre, lam, residual)


class Impact(eqx.Module):
    """Which contacts act in the step, when, and with which normal velocity target."""

    active: Bool[Array, " K"]
    toi: Float[Array, " K"]  # impact fraction s of the step
    target: Float[Array, " K"]  # normal velocity target (restitution)
    q: Float[Array, " 3K"]  # LCP offset: w = W P + q


def impact(frame: ContactFrame, resp: Responses, ball: Ball, settings: ContactSettings, h: float, flying) -> Impact:
    """Activity, time of impact and Newton's restitution target (see the module docstring)."""
    gap, uf_n, u_pre = frame.gap, resp.u_free[:, 0], resp.u_pre
    reach = h * jnp.maximum(-uf_n, 0.0)
    active = flying & ((gap <= 0.0) | (gap <= reach))
    toi = jnp.where(active & (gap > 0.0), jnp.clip(gap / jnp.maximum(reach, _TINY), 0.0, 1.0), 0.0)
    u_s = u_pre + toi * (uf_n - u_pre)
    bounce = -u_s > settings.restitution_threshold
    target = jnp.where(bounce, jnp.maximum(0.0, -ball.restitution * u_s + (1.0 - toi) * (uf_n - u_pre)), 0.0)
    target = jnp.where(active, target, 0.0)
    q = (resp.u_free - jnp.stack([target, jnp.zeros_like(target), jnp.zeros_like(target)], -1)).reshape(-1)
    return Impact(active, toi, target, q)


def _when_touching(active, solve, zeros):
    """``solve()`` when a contact is active, else zeros (a select under vmap, where both run)."""
    return jax.lax.cond(jnp.any(active), solve, lambda: zeros)


def contact_impulses(resp: Responses, imp: Impact, ball: Ball, settings: ContactSettings, warm):
    """The LCP by PGS, warm started: impulses (K, 3) and the normal slack w_n (K,)."""
    p = _when_touching(
        imp.active,
        lambda: solve_lcp_pgs(
            resp.w_mat, imp.q, ball.friction, imp.active, warm, settings.friction_directions, settings.pgs_iterations
        ),
        jnp.zeros_like(warm),
    )
    slack = (resp.w_mat @ p.reshape(-1) + imp.q).reshape(-1, 3)[:, 0]
    return p, slack


class Motion(eqx.Module):
    """Velocities after the impulses and displacements of the step (generalized, 6 per body)."""

    v_char: Float[Array, " 6B"]
    v_ball: Float[Array, " 6"]
    d_char: Float[Array, " 6B"]
    d_ball: Float[Array, " 6"]


def motion(
    frame: ContactFrame, resp: Responses, imp: Impact, p, free: BallFree, settings: ContactSettings, h: float
) -> Motion:
    """v+ = v_f + X P; displacement with the impact inside the step, then the projection of the
    remaining linearized penetration."""
    flat = p.reshape(-1)
    late = (p * (1.0 - imp.toi)[:, None]).reshape(-1)
    disp = h * (resp.v_free + resp.x_char @ late)
    disp_b = h * (free.v_free + resp.x_ball @ late)
    sel_n = jnp.arange(frame.sel.shape[0]) * 3
    g_end = frame.gap + h * resp.u_free[:, 0] + h * (resp.w_mat @ late)[sel_n]
    w_nn = resp.w_mat[sel_n][:, sel_n]
    mu_pos = _when_touching(
        imp.active,
        lambda: solve_gap_projection(w_nn, g_end, imp.active, settings.position_iterations),
        jnp.zeros_like(g_end),
    )
    push = jnp.zeros(flat.shape[0], flat.dtype).at[sel_n].set(mu_pos)
    disp = disp + resp.x_char @ push
    disp_b = jnp.where(free.flying, disp_b + resp.x_ball @ push, 0.0)
    return Motion(resp.v_free + resp.x_char @ flat, free.v_free + resp.x_ball @ flat, disp, disp_b)


def ball_after(bstate: BallState, free: BallFree, mo: Motion) -> BallState:
    """The ball at the step end; one that is not flying keeps its velocity and spin."""
    return BallState(
        bstate.pos + mo.d_ball[:3],
        quat_turn(bstate.quat, mo.d_ball[3:]),
        jnp.where(free.flying, mo.v_ball[:3], free.vel),
        jnp.where(free.flying, mo.v_ball[3:], free.omega),
    )


def contact_info(
    model: Model,
    scene: ContactScene,
    h: float,
    data: ContactData,
    free: BallFree,
    frame: ContactFrame,
    resp: Responses,
    imp: Impact,
    p,
    slack,
) -> ContactInfo:
    """The step's record over all candidates, with the gap at the impact instant from the
    configuration moved by s h v_free."""
    state, vf6 = data.state, resp.v_free.reshape(model.n_bodies, 6)
    sh, bidx = imp.toi * h, frame.body
    pb = state.pos[bidx] + sh[:, None] * vf6[bidx, :3]
    qb = quat_turn(state.quat[bidx], sh[:, None] * vf6[bidx, 3:])
    cb = data.ball.pos + sh[:, None] * jnp.where(free.flying, free.vel_free, 0.0)
    gap_imp = jax.vmap(
        lambda i, p_, q_, c_: single_gap(model, scene.capsules, scene.settings, scene.ball.radius, i, p_, q_, c_)
    )(frame.sel, pb, qb, cb)
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
    )


# ----------------------------------------------------------------------------- the step


def contact_step(sim: SimModel, params: Params, scene: ContactScene, data: ContactData) -> ContactData:
    """One step of Eq. 2 with the ball and its contacts: the ordinary step's stages, the contact
    rows added to the chosen solver's system (see the module docstring). ``info.lam`` holds the
    constraint forces of the contact-free solve."""
    model, h, k, state = sim.model, sim.options.h, data.k, data.state
    solver = solvers.get(sim.options.solver)
    eq = equations_of_motion(sim, params, data, solver)  # type: ignore[arg-type]  # ContactData has Data's fields
    free = ball_free_motion(model, scene.ball, h, sim.ref.time[k], k, data.ball)
    frame = contact_frame(model, scene, state, data.ball)
    resp = responses(solver, eq, frame, scene.ball, free, state.v)
    imp = impact(frame, resp, scene.ball, scene.settings, h, free.flying)
    p, slack = contact_impulses(resp, imp, scene.ball, scene.settings, data.warm[frame.sel])
    mo = motion(frame, resp, imp, p, free, scene.settings, h)
    n = model.n_bodies
    new, violation = integrate(sim, solver, k, state, mo.d_char.reshape(n, 6), mo.v_char.reshape(n, 6), params.pulses)
    record = contact_info(model, scene, h, data, free, frame, resp, imp, p, slack)
    return ContactData(
        k + 1,
        new,
        StepInfo(resp.residual, violation, eq.force, eq.points, resp.lam / h, eq.reflex),
        ball_after(data.ball, free, mo),
        jnp.zeros_like(data.warm).at[frame.sel].set(p),
        record,
        eq.history,
    )
