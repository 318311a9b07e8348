"""Sweeps on the ground: every run a contact rollout of the character on the config's ground (a
free root, ``[ground]``; the postural loop when ``[balance]`` is on), the same pulses and gains
as a pulse sweep, measured against the same gains without a perturbation. Besides d(t) each run
keeps what the ground and balance metrics read (:class:`~neuromotor.studies.balance.StandingTrace`):
the COM, the pelvis, which bodies touch the ground and the total normal impulse per step."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import PartitionSpec as P
from jaxtyping import Array, Bool, Float, Int

from neuromotor import compiler
from neuromotor.model.skeleton import Model
from neuromotor.physics import contact as ct
from neuromotor.physics.dynamics import Params, Reference, SimModel, StepOptions
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.sweep.grid import RunBatch
from neuromotor.studies.sweep.runner import AXIS, Sweeper, _Layout, _pose, _put

# The columns a run on the ground adds (after the recovery metrics): simulate's ground and
# balance metrics (docs/balance.md).
GROUND_METRICS = (
    "ground_peak_force_N",
    "ground_contact_fraction",
    "max_lcp_residual_mps",
    "lcp_residual_p95_mps",
    "fell",
    "fall_time_s",
    "fall_body",
    "sway_rms_mm",
    "sway_range_ap_mm",
    "sway_range_ml_mm",
    "sway_rms_late_mm",
    "com_response_peak_mm",
    "com_response_time_s",
    "com_response_final_mm",
    "diverged_s",
)


class GroundRunOut(eqx.Module):
    """What a rollout on the ground leaves behind in a sweep (per run)."""

    pose: Float[Array, "S1 ..."]  # as RunOut.pose
    diverged_step: Int[Array, ""]
    diverged_body: Int[Array, ""]
    max_residual: Float[Array, ""]
    max_violation: Float[Array, ""]
    com: Float[Array, "S1 3"]  # whole-body COM (world)
    root_pos: Float[Array, "S1 3"]
    root_vel: Float[Array, "S1 3"]
    touch: Float[Array, "S1 B"]  # each body's normal impulse from the ground (N s)
    total: Float[Array, " S1"]  # the ground's total normal impulse (N s)
    lcp_residual: Float[Array, " S1"]  # each step's largest LCP residual (m/s)
    touching: Bool[Array, " S1"]  # each step had an active contact


class GroundSweeper(Sweeper):
    """:class:`Sweeper` of contact rollouts on a ground: runs are (gains, pulses) pairs like a
    pulse sweep's; the ground is shared by all of them (an argument of the program: sweeps of
    one skeleton and ground layout share their program)."""

    def __init__(self, model: Model, ref: Reference, options: StepOptions, ground: ct.Ground, **kw):
        self.scene = ground_scene(ground)
        super().__init__(model, ref, options, **kw)
        arrays, self.scene_static = eqx.partition(self.scene, eqx.is_array)
        self.shared = (*self.shared, jax.tree_util.tree_map(lambda x: _put(x, self.mesh, P()), arrays))
        self._simulate = _ground_program(
            _Layout(self.model_static),
            _Layout(self.scene_static),
            self.options,
            self.metric,
            self.inner_batch,
            self.mesh,
        )

    def _program(self, static):
        self.model_static = static
        return None  # built in __init__, once the scene is placed


@functools.lru_cache(maxsize=16)
def _ground_program(layout: _Layout, scene_layout: _Layout, options: StepOptions, metric: str, inner_batch: int, mesh):
    """``f(shared, batch) -> GroundRunOut``: :func:`~neuromotor.studies.sweep.runner._chunk_program`
    with contact rollouts on the shared ground."""

    def one(shared, run: RunBatch) -> GroundRunOut:
        model = eqx.combine(shared[0], layout.static)
        scene = eqx.combine(shared[2], scene_layout.static)
        r = ct.simulate_contact(SimModel(model, shared[1], options), Params(run.gains, run.pulses), scene)
        ground = scene.ground
        lam = r.contact.normal_impulse[:, -ground.n_slots :]
        touch = jnp.zeros(lam.shape[:1] + (model.n_bodies,), lam.dtype).at[:, ground.slot_body].add(lam)
        states = r.run.states
        return GroundRunOut(
            _pose(metric, model, r.run),
            r.run.diverged_step,
            r.run.diverged_body,
            jnp.max(r.run.residual),
            jnp.max(r.run.violation),
            jnp.einsum("b,tbi->ti", model.mass / jnp.sum(model.mass), states.pos),
            states.pos[:, 0],
            states.vel[:, 0],
            touch,
            jnp.sum(lam, -1),
            r.contact.step_residual,
            r.contact.touching,
        )

    def local(shared, batch: RunBatch) -> GroundRunOut:
        return jax.lax.map(functools.partial(one, shared), batch, batch_size=None if inner_batch == 1 else inner_batch)

    return compiler.jit(jax.shard_map(local, mesh=mesh, in_specs=(P(), P(AXIS)), out_specs=P(AXIS), check_vma=False))


def ground_row_metrics(setup, batch: RunBatch, i: int, out: dict) -> dict:
    """Run i's ground and balance metrics, as ``simulate`` reports them (the COM relative to a
    moving ground's displacement, :func:`~neuromotor.studies.ground.platform_offset`)."""
    from neuromotor.studies.balance import StandingTrace, balance_metrics
    from neuromotor.studies.ground import ground_figures, lcp_figures

    time = np.asarray(setup.ref.time)[: setup.options.n_steps + 1]
    com = np.asarray(out["com"])
    offset = batch.pulses.base_offset
    if setup.options.free_root and offset is not None:  # a base motion moves the ground
        com = com - np.asarray(offset)[i][: com.shape[0]]
    touch = np.asarray(out["touch"]) > 0
    # The row's own base motion (the sweep may vary it): the assist's target moves with it.
    pulses, n = batch.pulses, com.shape[0]
    base = None if pulses.base_offset is None else np.asarray(pulses.base_offset)[i][:n]
    base_vel = None if pulses.base_velocity is None else np.asarray(pulses.base_velocity)[i][:n]
    trace = StandingTrace(
        time,
        com,
        touch,
        np.asarray(out["root_pos"]),
        np.asarray(out["root_vel"]),
        int(out["diverged_step"]),
        base,
        base_vel,
    )
    lcp = lcp_figures(out["lcp_residual"], out["touching"])
    return ground_figures(out["total"], setup.options.h) | lcp | balance_metrics(setup, trace, base=out["base_com"])
