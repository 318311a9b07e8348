"""The contact rollout: the ordinary scan (:func:`neuromotor.physics.dynamics.scan_steps`) of
the contact step, the ball's state and the contact record carried beside the character's."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from neuromotor import compiler
from neuromotor.model.skeleton import Model
from neuromotor.physics.contact.ball import Ball, BallState
from neuromotor.physics.contact.detection import ContactSettings
from neuromotor.physics.contact.shapes import Capsules
from neuromotor.physics.contact.step import ContactInfo, ContactScene, contact_step, initial_contact_data
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import (Params, Reference, Rollout, StepOptions, SimModel, SimulationDiverged,
                                         init_data, rollout_of, scan_steps)
from neuromotor.physics.perturbation import ForcePulses, no_pulses
from neuromotor.physics.precision import cast


class ContactRollout(eqx.Module):
    """The character's :class:`Rollout` plus the ball and the contact record (leading S+1)."""

    run: Rollout
    ball: BallState
    contact: ContactInfo  # row 0: no impulse, the initial gaps


def contact_rollout(model: Model, gains: Gains, pulses: ForcePulses | None, ref: Reference,
                    cfg: StepOptions, ball: Ball, caps: Capsules, settings: ContactSettings) -> ContactRollout:
    """``cfg.n_steps`` steps of :func:`~neuromotor.physics.contact.step.contact_step` in one ``lax.scan``."""
    sim = SimModel(model, ref, cfg)
    params = Params(gains, no_pulses() if pulses is None else pulses)
    # The precision of cfg.dtype for the character, the ball and the capsules alike.
    sim, params, scene = cast((sim, params, ContactScene(ball, caps, settings)), cfg.dtype)
    data0 = initial_contact_data(model, scene, init_data(sim, params))
    out, bad_step, bad_body = scan_steps(sim, params, data0, lambda s, p, d: contact_step(s, p, scene, d))
    stack = lambda a, b: jnp.concatenate([a[None], b], 0)
    return ContactRollout(rollout_of(sim, data0, out, bad_step, bad_body),
                          jax.tree_util.tree_map(stack, data0.ball, out.ball),
                          jax.tree_util.tree_map(stack, data0.contact, out.contact))


def check_contact_rollout(model: Model, out: ContactRollout) -> ContactRollout:
    """Raise :class:`SimulationDiverged` naming the step and the body (or ``ball``)."""
    step_ = int(out.run.diverged_step)
    if step_ >= 0:
        b = int(out.run.diverged_body)
        name = model.body_names[b] if b < model.n_bodies else "ball"
        raise SimulationDiverged(step_, float(out.run.time[step_ + 1]), name)
    return out


contact_rollout_jit = compiler.jit(contact_rollout, static_argnames=("cfg", "settings"))
# One compiled, vmapped rollout over a batch of balls (leading axis), everything else shared.
batched_contact_rollout = compiler.jit(
    jax.vmap(contact_rollout, in_axes=(None, None, None, None, None, 0, None, None)), static_argnums=(4, 7))
