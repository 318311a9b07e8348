"""The grid of a sweep as a batch: one row of gains (with the run's reflex, when the grid varies
it) and force pulses per run, and the shared unperturbed twin of each distinct controller."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.errors import ConfigError
from neuromotor.physics.control import Gains
from neuromotor.physics.perturbation import ForcePulses, build_pulses, stack_runs, vector_direction
from neuromotor.physics.reflex import Reflex
from neuromotor.studies.gains import gains_for

METRIC_KEYS = (
    "peak_deviation_deg",
    "time_of_peak_s",
    "recovery_time_s",
    "final_error_deg",
    "overshoot_deg",
    "recovery_threshold_deg",
)


# The columns every sweep table has: the run and its inputs, then (after each kind's own) the
# step's diagnostics and divergence.
RUN_COLUMNS = (
    "run",
    "kind",
    "label",
    "controller",
    "ks",
    "kd",
    "body",
    "magnitude",
    "direction_x",
    "direction_y",
    "direction_z",
    "start",
)
DIAGNOSTIC_COLUMNS = (
    "max_kkt_residual",
    "max_constraint_violation",
    "diverged",
    "diverged_step",
    "diverged_time_s",
    "diverged_body",
)
COLUMNS = (*RUN_COLUMNS, "duration", *METRIC_KEYS, *DIAGNOSTIC_COLUMNS)


# The reflex of a run (neuromotor.physics.reflex), written when the config has a [reflex] table.
REFLEX_COLUMNS = ("reflex_gain", "reflex_delay", "long_latency_gain", "long_latency_delay")


def with_reflex_columns(columns: Sequence[str]) -> tuple[str, ...]:
    """``columns`` with :data:`REFLEX_COLUMNS` after the muscle gains (ks, kd)."""
    i = list(columns).index("kd") + 1
    return (*columns[:i], *REFLEX_COLUMNS, *columns[i:])


BALL_COLUMNS = (
    *RUN_COLUMNS,
    *METRIC_KEYS,
    "peak_impulse_Ns",
    "hit_body",
    "first_contact_s",
    "max_lcp_residual_mps",
    "lcp_residual_p95_mps",
    *DIAGNOSTIC_COLUMNS,
)


class RunBatch(eqx.Module):
    """Inputs of a batch of runs: every leaf has a leading run axis."""

    gains: Gains
    pulses: ForcePulses


class RunOut(eqx.Module):
    """What a rollout leaves behind in a sweep (per run). ``pose``: what the deviation is
    measured on, the joints' local quaternions (S1, C, 4) (geodesic metric) or the Euler angles
    theta (S1, n) (``metric = "euler"``)."""

    pose: Float[Array, "S1 ..."]
    diverged_step: Int[Array, ""]
    diverged_body: Int[Array, ""]
    max_residual: Float[Array, ""]
    max_violation: Float[Array, ""]


def _stack(trees: Sequence[Any]):
    return jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def run_controller(template_gains: Gains, run: dict, h: float | None) -> Gains:
    """The gains of one run: its gain setting and, when the grid varies it, its reflex
    (a :class:`~neuromotor.config.specs.ReflexSpec` built at step ``h``)."""
    rx = run.get("reflex")
    if rx is not None and h is None:
        raise ValueError("a run with a reflex setting needs the step h to build its history")
    return gains_for(template_gains, run["gain"], reflex=None if rx is None else rx.build(h))


def reflex_columns(run: dict, template: Reflex | None) -> dict:
    """The :data:`REFLEX_COLUMNS` of a run: its own reflex setting, else the template's (none: {})."""
    rx = run.get("reflex")
    if rx is not None:
        return dict(zip(REFLEX_COLUMNS, (rx.gain, rx.delay, rx.long_latency_gain, rx.long_latency_delay)))
    if template is None:
        return {}
    paths = (template.spinal.gain, template.spinal.delay, template.long_latency.gain, template.long_latency.delay)
    return dict(zip(REFLEX_COLUMNS, (float(x) for x in paths)))


def build_batch(
    template_gains: Gains,
    template_pulses: ForcePulses,
    runs: list[dict],
    body_index,
    h: float,
    model,
    direction_of=vector_direction,
    times=None,
    pivot=None,
) -> RunBatch:
    """Batched gains and perturbations for ``runs`` (:meth:`~neuromotor.config.specs.SweepSpec.runs`):
    each run's ``perturbations`` (its varied ``perturbation`` with the grid's axes applied, then
    the config's others) through the one builder,
    :func:`~neuromotor.physics.perturbation.build_pulses` at step ``h`` on ``model`` and the
    grid ``times`` (a base motion needs them) and a tilt's default ``pivot``; the reflex, for
    runs that carry one, is built at step ``h``."""
    if template_pulses.count == 0 and template_pulses.base_velocity is None:
        raise ConfigError("a sweep needs at least one [[perturbation]] to vary")
    settings = {}
    for r in runs:
        key = (r["gain"], r.get("reflex"))
        if key not in settings:
            settings[key] = run_controller(template_gains, r, h)
    gains = _stack([settings[(r["gain"], r.get("reflex"))] for r in runs])
    rows = [build_pulses(r["perturbations"], model, h, body_index, direction_of, times, pivot) for r in runs]
    return RunBatch(gains, stack_runs(rows))


def gain_keys(batch: RunBatch) -> tuple[np.ndarray, np.ndarray]:
    """Index of the first run with identical gains (the baseline to share) and each run's slot."""
    leaves = [
        np.asarray(x).reshape(np.asarray(batch.pulses.magnitude).shape[0], -1)
        for x in jax.tree_util.tree_leaves(batch.gains)
    ]
    flat = np.concatenate(leaves, axis=1)
    _, first, slot = np.unique(flat, axis=0, return_index=True, return_inverse=True)
    return first, slot.reshape(-1)
