"""The contact rollout: the ordinary scan (:func:`neuromotor.physics.dynamics.scan_steps`) of
the contact step, the ball's state and the contact record carried beside the character's."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from neuromotor import compiler
from neuromotor.model.skeleton import Model
from neuromotor.physics.contact.ball import BallState
from neuromotor.physics.contact.step import ContactInfo, ContactScene, contact_step, initial_contact_data
from neuromotor.physics.dynamics import Params, Rollout, SimModel, SimulationDiverged, init_data, rollout_of, scan_steps
from neuromotor.physics.precision import cast


class ContactRollout(eqx.Module):
    """The character's :class:`Rollout` plus the ball (None: no ball) and the contact record
    (leading S+1)."""

    run: Rollout
    ball: BallState | None
    contact: ContactInfo  # row 0: no impulse, the initial gaps


def simulate_contact(sim: SimModel, params: Params, scene: ContactScene) -> ContactRollout:
    """``sim.options.n_steps`` steps of :func:`~neuromotor.physics.contact.step.contact_step` in one
    ``lax.scan``: :func:`~neuromotor.physics.dynamics.simulate` with the ``scene`` (ball,
    capsules, settings, ground) beside the character."""
    # The precision of options.dtype for the character, the ball and the capsules alike.
    sim, params, scene = cast((sim, params, scene), sim.options.dtype)
    data0 = initial_contact_data(sim.model, scene, init_data(sim, params))
    out, bad_step, bad_body = scan_steps(sim, params, data0, lambda s, p, d: contact_step(s, p, scene, d))
    stack = lambda a, b: jnp.concatenate([a[None], b], 0)
    return ContactRollout(
        rollout_of(sim, data0, out, bad_step, bad_body),
        jax.tree_util.tree_map(stack, data0.ball, out.ball),
        jax.tree_util.tree_map(stack, data0.contact, out.contact),
    )


def check_contact_rollout(model: Model, out: ContactRollout) -> ContactRollout:
    """Raise :class:`SimulationDiverged` naming the step and the body (or ``ball``)."""
    step_ = int(out.run.diverged_step)
    if step_ >= 0:
        b = int(out.run.diverged_body)
        name = model.body_names[b] if b < model.n_bodies else "ball"
        raise SimulationDiverged(step_, float(out.run.time[step_ + 1]), name)
    return out


simulate_contact_jit = compiler.jit(simulate_contact)


def _over_balls(sim: SimModel, params: Params, scene: ContactScene) -> ContactRollout:
    return jax.vmap(lambda ball: simulate_contact(sim, params, dataclasses.replace(scene, ball=ball)))(scene.ball)


# One compiled, vmapped rollout over a batch of balls (``scene.ball``'s leading axis), the rest shared.
batched_simulate_contact = compiler.jit(_over_balls)
