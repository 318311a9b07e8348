"""A ball thrown at the character in a run: the ``[ball]`` table made into a ball (aimed at a
body when it names a target), its perturbed and unperturbed contact rollouts and metrics, its
part of RUN.npz, and a quick vmapped sweep over its speed.

The physics (shapes, detection, LCP, the contact step and rollout) is
:mod:`neuromotor.physics.contact`; :mod:`neuromotor.studies.simulate` calls this module for a
config with a ``[ball]`` table.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from neuromotor import compiler
from neuromotor.config import ConfigError
from neuromotor.model.facing import resolve_direction
from neuromotor.model.kinematics import body_poses
from neuromotor.model.skeleton import Character, Model
from neuromotor.physics.contact import (
    Ball,
    Capsules,
    ContactRollout,
    ContactScene,
    ContactSettings,
    Ground,
    batched_simulate_contact,
    candidate_bodies,
    candidate_names,
    check_contact_rollout,
    detect,
    fit_capsules,
    make_ball,
    never_launched,
    on_character as candidates_on_character,
    simulate_contact_jit,
)
from neuromotor.physics.dynamics import Params
from neuromotor.rotations import quat_to_matrix
from neuromotor.studies import metrics as mx


class BallSetup(eqx.Module):
    """What :func:`neuromotor.studies.simulate.prepare` keeps for a ``[ball]`` config."""

    ball: Ball
    capsules: Capsules
    settings: ContactSettings = eqx.field(static=True)
    target: int | None = eqx.field(static=True, default=None)  # body the ball is aimed at
    ground: Ground | None = None  # the bodies' ground, when they touch it ([ground])

    def scene(self, ball: Ball | None = None) -> ContactScene:
        """What the contact step adds to the character: ``ball`` (default: this one), the capsules,
        the settings, and the bodies' ground if any."""
        return ContactScene(self.ball if ball is None else ball, self.capsules, self.settings, self.ground)

    @property
    def n_candidates(self) -> int:
        """The ball's candidates (capsules, then its ground); the bodies' ground slots follow."""
        return self.capsules.radius.shape[0] + int(self.settings.ground)


# ----------------------------------------------------------------------------- aiming


@compiler.jit
def _com_at(model: Model, traj, body, t):
    return body_poses(model, traj.q(t))[0][body]


def aim_ball(
    model: Model, traj, position, speed: float, target_body: int, launch: float, iterations: int = 20
) -> np.ndarray:
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
        raise ValueError(
            f"is too low: a ball at {speed:g} m/s cannot reach the target from {position.tolist()} "
            f"(the aim does not converge)"
        )
    return d / np.linalg.norm(d)


# ----------------------------------------------------------------------------- the [ball] table


def _aims(spec) -> bool:
    """Whether the table aims the ball at a body; ValueError when its speed cannot."""
    if "velocity" in spec or "target" not in spec:
        return False
    if not spec["speed"] > 0:
        raise ValueError("must be > 0 to aim at a target")
    return True


def ball_from_spec(spec, model: Model, traj, target: int | None = None) -> Ball:
    """The :class:`Ball` of a parsed ``[ball]`` table; aimed at body ``target`` when the table
    names one. Raises ValueError when the aim is impossible (speed <= 0, or too slow to reach it)."""
    if "velocity" in spec:
        return make_ball(
            spec["radius"],
            spec["mass"],
            spec["position"],
            velocity=spec["velocity"],
            restitution=spec["restitution"],
            friction=spec["friction"],
            launch=spec["launch"],
        )
    direction = spec.get("direction")
    if _aims(spec):
        assert target is not None, "a [ball] table that names a target needs its body index"
        direction = aim_ball(model, traj, spec["position"], spec["speed"], target, spec["launch"])
    return make_ball(
        spec["radius"],
        spec["mass"],
        spec["position"],
        speed=spec["speed"],
        direction=direction,
        restitution=spec["restitution"],
        friction=spec["friction"],
        launch=spec["launch"],
    )


def ball_setup(
    spec, character: Character, traj, body_index, source: str = "config", still: float | None = None
) -> BallSetup:
    """Build the ball from a parsed ``[ball]`` table (see :func:`neuromotor.config.parse_ball`);
    ``body_index`` maps a body name to its index (raising ConfigError for an unknown one);
    ``still``: the clip time of a held pose (``[sim] still``), whose frame a keyword direction is in."""
    model = character.model
    if isinstance(spec.get("direction"), str):  # a keyword of the character's frame at launch
        where = f"{source}: field 'ball.direction'"
        at = float(spec["launch"]) if still is None else float(still)
        spec = dict(spec, direction=resolve_direction(spec["direction"], character, at, where))
    try:
        target = body_index(spec["target"]) if _aims(spec) else None
        ball = ball_from_spec(spec, model, traj, target)
    except ConfigError:
        raise
    except ValueError as e:
        raise ConfigError(f"{source}: field 'ball.speed' {e}") from None
    settings = ContactSettings(
        friction_directions=spec["friction_directions"],
        max_contacts=spec["max_contacts"],
        pgs_iterations=spec["pgs_iterations"],
        restitution_threshold=spec["restitution_threshold"],
        ground=spec["ground"],
        ground_height=spec["ground_height"],
    )
    return BallSetup(ball, fit_capsules(character), settings, target)


def balls_at_speeds(setup, speeds) -> Ball:
    """The config's ball at each speed (leading axis = speed): exactly the ball that
    ``simulate.prepare`` builds for the config with ``ball.speed`` set to that speed. A ball
    aimed at a ``target`` is re-aimed per speed (a slower ball needs a higher arc); a
    ``direction`` or ``velocity`` keeps its direction. Raises ValueError for a speed that
    cannot reach the target."""
    spec = dict(setup.config.ball)
    if "velocity" in spec or isinstance(spec.get("direction"), str):  # the direction the setup resolved
        spec["direction"] = np.asarray(setup.ball.ball.direction).tolist()
        del spec["velocity"]
    balls = []
    for s in speeds:
        try:
            balls.append(ball_from_spec(dict(spec, speed=float(s)), setup.model, setup.traj, setup.ball.target))
        except ValueError as e:
            raise ValueError(f"speed {float(s):g} m/s {e}") from None
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *balls)


# ----------------------------------------------------------------------------- a run


def ball_rollouts(setup, base_pulses, check: bool = True) -> tuple[ContactRollout, ContactRollout]:
    """Perturbed (the ball flies) and unperturbed (the ball never launched, ``base_pulses``:
    the config's pulses switched off) contact rollouts, with the same compiled function."""
    bs, model, sim = setup.ball, setup.model, setup.sim_model
    pert = simulate_contact_jit(sim, setup.params, bs.scene())
    base = simulate_contact_jit(sim, Params(setup.gains, base_pulses), bs.scene(never_launched(bs.ball)))
    if check:
        check_contact_rollout(model, base)
        check_contact_rollout(model, pert)
    return pert, base


def on_character(bs: BallSetup) -> np.ndarray:
    """(C,) bool over the ball's candidates: a body of the character (not the ground)."""
    return np.asarray(candidates_on_character(bs.capsules, bs.settings))


def ball_metrics(out: ContactRollout, bs: BallSetup) -> dict:
    """The metrics a ball adds to a run's: its peak one-step impulse on a body of the character
    and the time of its first contact with one (the ball's bounces on the ground left out, as
    the ball-speed sweep's rows leave them)."""
    on = on_character(bs)
    lam = np.asarray(out.contact.normal_impulse[:, : on.shape[0]]) * on
    imp = np.linalg.norm(np.asarray(out.contact.impulse[:, : on.shape[0]]), axis=-1) * on
    hit = np.nonzero(lam.max(-1) > 0)[0]
    return {
        "ball_peak_impulse_Ns": float(imp.max()),
        "ball_first_contact_s": float(out.run.time[hit[0]]) if hit.size else None,
    }


def ball_arrays(setup, result) -> dict[str, np.ndarray]:
    """The ball's part of RUN.npz: ``ball_pos`` (T,3), ``ball_quat``, ``ball_vel``,
    ``ball_radius``, per contact candidate ``contact_impulse`` / ``contact_force`` (T,C,3, on
    the ball, world; the body gets the opposite), ``contact_point`` (T,C,3, on the body),
    ``contact_normal_impulse``, ``contact_gap`` (T,C), ``contact_body`` (C, -1 = ground),
    ``contact_names`` (C)."""
    out: ContactRollout = result.ball
    bs: BallSetup = setup.ball
    assert out.ball is not None  # a ball run
    c = jax.tree_util.tree_map(lambda x: x[:, : bs.n_candidates], out.contact)  # the ball's candidates
    impulse = np.asarray(c.impulse)
    model = setup.model
    # Closest points on the bodies (and the ground) to the ball, for drawing the force arrows.
    points = np.asarray(
        jax.vmap(
            lambda p, q, centre: detect(model, bs.capsules, bs.settings, bs.ball.radius, centre, p, quat_to_matrix(q))[
                2
            ]
        )(out.run.states.pos, out.run.states.quat, out.ball.pos)
    )
    return {
        "ball_pos": np.asarray(out.ball.pos),
        "ball_quat": np.asarray(out.ball.quat),
        "ball_vel": np.asarray(out.ball.vel),
        "ball_radius": np.asarray(float(bs.ball.radius)),
        "contact_impulse": impulse,
        "contact_force": impulse / setup.options.h,
        "contact_normal_impulse": np.asarray(c.normal_impulse),
        "contact_point": points,
        "contact_gap": np.asarray(c.gap),
        "contact_body": np.asarray(candidate_bodies(bs.capsules, bs.settings)),
        "contact_names": np.array(candidate_names(bs.capsules, bs.settings)),
    }


def sweep_ball_speed(setup, speeds) -> dict[str, np.ndarray]:
    """Ball speed as the perturbation magnitude: one vmapped batch of contact rollouts.

    The batch holds one run per speed plus the unperturbed run (the ball never launched), so a
    single compiled function serves them all. The ball keeps its direction (no re-aiming).
    Returns per speed the peak deviation from the unperturbed run (by ``[sim] metric``: RMS
    over joints of the geodesic angle, or over Euler DOFs; degrees), its time, and the peak
    one-step impulse on a body of the character (ground bounces left out)."""
    bs = setup.ball
    on = on_character(bs)
    speeds = jnp.asarray(speeds, jnp.float64)
    balls = jax.vmap(lambda s: eqx.tree_at(lambda b: b.speed, bs.ball, s))(speeds)
    balls = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b[None]]), balls, never_launched(bs.ball))
    batch = batched_simulate_contact(setup.sim_model, setup.params, bs.scene(balls))
    if setup.config.metric == "euler":
        theta = batch.run.theta
        dev = jax.vmap(lambda th: mx.deviation(th, theta[-1]))(theta[:-1])
    else:
        quat = batch.run.states.quat
        dev = jax.vmap(lambda q: mx.joint_deviation(setup.model, q, quat[-1]))(quat[:-1])
    return {
        "speed": np.asarray(speeds),
        "peak_deviation_deg": np.asarray(jnp.max(dev, -1)),
        "time_of_peak_s": np.asarray(batch.run.time[0])[np.asarray(jnp.argmax(dev, -1))],
        "peak_impulse_Ns": np.max(
            np.linalg.norm(np.asarray(batch.contact.impulse[:-1, :, : on.shape[0]]), axis=-1) * on, axis=(1, 2)
        ),
    }
