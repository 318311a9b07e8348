"""Ball-speed sweeps: every run a contact rollout of the config's ball at one speed, measured
against the same gains with the ball never launched."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Bool, Float, Int

from neuromotor import compiler
from neuromotor.config.specs import GainSetting
from neuromotor.model.skeleton import Model
from neuromotor.physics import contact as ct
from neuromotor.physics.control import Gains
from neuromotor.physics.dynamics import Params, Reference, SimModel, StepOptions
from neuromotor.physics.perturbation import ForcePulses
from neuromotor.studies import metrics as mx
from neuromotor.studies.gains import gains_for
from neuromotor.studies.ground import lcp_figures
from neuromotor.studies.sweep.grid import _stack
from neuromotor.studies.sweep.runner import AXIS, Sweeper, SweepResult, sweep_batches


class BallBatch(eqx.Module):
    """Inputs of a batch of ball runs: every leaf has a leading run axis."""

    gains: Gains
    ball: ct.Ball


class BallRunOut(eqx.Module):
    """What a contact rollout leaves behind in a sweep (per run)."""

    pose: Float[Array, "S1 ..."]  # as RunOut.pose
    diverged_step: Int[Array, ""]
    diverged_body: Int[Array, ""]  # n_bodies: the ball
    max_residual: Float[Array, ""]
    max_violation: Float[Array, ""]
    peak_impulse: Float[Array, ""]  # largest |impulse| of one step on a body of the character (N s)
    hit_body: Int[Array, ""]  # the body that received it; -1: the ball never touched the character
    first_contact: Int[Array, ""]  # first sample with a contact on the character; -1: none
    lcp_residual: Float[Array, " S1"]  # each step's largest LCP residual (m/s)
    touching: Bool[Array, " S1"]  # each step had an active contact


class BallSweeper(Sweeper):
    """:class:`Sweeper` of contact rollouts: runs are (gains, ball) pairs, the capsules, contact
    settings and (empty) force pulses are shared by all of them."""

    def __init__(self, model: Model, ref: Reference, options: StepOptions, ball_setup, pulses: ForcePulses, **kw):
        self.capsules, self.settings, self.pulses = ball_setup.capsules, ball_setup.settings, pulses
        super().__init__(model, ref, options, **kw)

    def _program(self, static):
        self.model_static = static  # the contact rollout closes over this sweeper's ball set-up
        local = lambda shared, batch: jax.lax.map(
            functools.partial(self._one, shared), batch, batch_size=None if self.inner_batch == 1 else self.inner_batch
        )
        return compiler.jit(
            jax.shard_map(local, mesh=self.mesh, in_specs=(P(), P(AXIS)), out_specs=P(AXIS), check_vma=False)
        )

    def _one(self, shared, run: BallBatch) -> BallRunOut:
        model = eqx.combine(shared[0], self.model_static)
        r = ct.simulate_contact(
            SimModel(model, shared[1], self.options),
            Params(run.gains, self.pulses),
            ct.ContactScene(run.ball, self.capsules, self.settings),
        )
        bodies = ct.candidate_bodies(self.capsules, self.settings)
        on_char = ct.on_character(self.capsules, self.settings)
        imp = jnp.linalg.norm(r.contact.impulse, axis=-1) * on_char  # (S+1, C)
        peak = jnp.max(imp)
        cand = jnp.argmax(jnp.max(imp, axis=0))
        touched = jnp.any((r.contact.normal_impulse > 0) & on_char, axis=-1)
        return BallRunOut(
            self.pose(model, r.run),
            r.run.diverged_step,
            r.run.diverged_body,
            jnp.max(r.run.residual),
            jnp.max(r.run.violation),
            peak,
            jnp.where(peak > 0, bodies[cand], -1),
            jnp.where(jnp.any(touched), jnp.argmax(touched), -1),
            r.contact.step_residual,
            r.contact.touching,
        )


def run_ball_sweep(
    sweeper: BallSweeper,
    setup,
    speeds: Sequence[float],
    gain_settings: Sequence[GainSetting],
    *,
    balls: ct.Ball | None = None,
    keep_curves: bool = False,
    progress: bool = True,
) -> SweepResult:
    """Contact rollouts of the config's ball at every speed x gain setting (gain setting
    outermost), chunked like :func:`~neuromotor.studies.sweep.run_sweep`, measured against the
    ball never launched. ``balls``: :func:`neuromotor.studies.ball_hit.balls_at_speeds` of ``speeds``,
    if already built."""
    from tqdm.auto import tqdm

    from neuromotor.studies.ball_hit import balls_at_speeds

    body_names = setup.model.body_names
    speeds = [float(v) for v in speeds]
    if balls is None:
        balls = balls_at_speeds(setup, speeds)  # (n_speeds,) leaves
    runs = [(g, i) for g in gain_settings for i in range(len(speeds))]
    settings = {g: gains_for(setup.gains, g) for g in gain_settings}
    take = np.array([i for _, i in runs])
    balls = jax.tree_util.tree_map(lambda x: np.asarray(x)[take], balls)
    batch = BallBatch(_stack([settings[g] for g, _ in runs]), balls)
    slot = np.array([list(settings).index(g) for g, _ in runs])
    # Twins: one per gain setting, the ball never launched (no contact, no force at all).
    base = BallBatch(_stack(list(settings.values())), _stack([ct.never_launched(setup.ball.ball)] * len(settings)))
    launch, target = float(setup.ball.ball.launch), setup.config.ball.get("target", "")
    direction = np.asarray(batch.ball.direction)

    def row(i: int, out: dict, dev, time) -> dict:
        (g, k), hit, first = runs[i], int(out["hit_body"]), int(out["first_contact"])
        return {
            "run": i,
            "kind": "ball",
            "label": g.name,
            "controller": g.controller,
            "ks": g.ks,
            "kd": g.kd,
            "body": target,
            "magnitude": speeds[k],
            "direction_x": float(direction[i, 0]),
            "direction_y": float(direction[i, 1]),
            "direction_z": float(direction[i, 2]),
            "start": launch,
            **mx.recovery_metrics(time, dev, launch),
            "peak_impulse_Ns": float(out["peak_impulse"]),
            "hit_body": body_names[hit] if hit >= 0 else "",
            "first_contact_s": float(time[first]) if first >= 0 else float("nan"),
            **lcp_figures(out["lcp_residual"], out["touching"]),
            "max_kkt_residual": float(out["max_residual"]),
            "max_constraint_violation": float(out["max_violation"]),
        }

    def body(out: dict) -> str:  # n_bodies: the ball
        b = int(out["diverged_body"])
        return body_names[b] if b < len(body_names) else "ball"

    bar = tqdm(total=len(settings) + len(runs), desc="ball sweep", unit="run", disable=not progress)
    return sweep_batches(sweeper, batch, base, slot, row, body, bar, keep_curves)
