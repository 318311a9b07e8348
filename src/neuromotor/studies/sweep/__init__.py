"""Batch sweeps: many perturbed rollouts as one jitted computation, sharded over all devices.

A sweep is a flat list of runs. Each run is a :class:`~neuromotor.physics.control.Gains` and a
:class:`~neuromotor.physics.perturbation.ForcePulses` (same static layout for all runs; the first pulse
is the one a grid varies). Runs go through the device(s) in chunks:

* the batch axis of a chunk is sharded over the process's devices (``jax.local_devices()``)
  with a 1-D :class:`jax.sharding.Mesh` and :func:`jax.shard_map`, so the same code spreads
  over several GPUs, or over the cores of a CPU (the command line gives JAX one CPU device per
  core, :func:`neuromotor.compiler.use_cpu_cores`); steps that call LAPACK stay on one device
  (:func:`neuromotor.physics.solvers.uses_lapack`);
* with several processes (one per host or GPU, or several on one machine, after
  :func:`neuromotor.distributed.initialize`) each simulates its contiguous share of the runs
  and the shares are gathered with ``multihost_utils.process_allgather``; every process gets
  the rows in grid order and process 0 writes the files (:mod:`neuromotor.distributed`);
* inside each shard the rollouts run under :func:`jax.lax.map` (``inner_batch`` > 1 vmaps
  groups of that size inside the loop, with the ``nullspace`` solver's batched twin ``branch``:
  about 3.5x the throughput of single runs at 256 on a 2-core CPU, docs/benchmarks.md).
  Batched LAPACK calls on two host CPU devices at once can deadlock in XLA:CPU (a vmapped
  ``jnp.linalg.solve`` under GSPMD, or inside ``shard_map``): hence LAPACK steps on one device;
* only a deviation curve d(t) (S+1 floats) and four diagnostics come back per run, so device
  memory stays bounded by the chunk size whatever the grid size; the exact recovery metrics
  (:func:`neuromotor.studies.metrics.recovery_metrics`) are computed on the host from them.

The deviation of a run is measured against its unperturbed twin: the same gains without any
pulse. Twins are shared: one baseline rollout per distinct gain setting, simulated first with
the same compiled program; their joint angles ((S+1) x n floats each) are the only per-setting
arrays kept for the whole sweep.

Runs that blow up (or whose baseline does) are kept and flagged: ``diverged`` is true, the
step, time and body are recorded, and the metric columns hold NaN.

Config (``[sweep]`` table of a simulation config; the grid is the Cartesian product)::

    [sweep]
    magnitudes = {start = 0.0, stop = 800.0, num = 9}   # or a list; N (or N s for impulses)
    directions = [[0.0, 0.0, 1.0]]    # default: perturbation[0].direction
    bodies = ["Chest2"]               # default: perturbation[0].body
    starts = [1.0]                    # default: perturbation[0].start
    ks = [400.0]                      # 1/s^2; a list or {start, stop, num, log = true}
    kd = [20.0]                       # 1/s; the gains grid is ks x kd ...
    # ... or explicit gain settings instead of ks x kd:
    # [[sweep.gains]]
    # label = "feedforward + low gain"; ks = 400.0; kd = 20.0; controller = "neuromotor"  # or "pd"
    chunk = 64                        # runs per device call (rounded up to a multiple of devices)
    inner_batch = 1                   # rollouts vmapped together inside each shard's loop (64-256: faster)
    output = "out/sweep"              # folder for sweep.csv and the plots (relative to the config)
    fitted = "fit.json"               # optional: fitted (ks, kd) to mark on the gains map, or [ks, kd]
    # With a [reflex] table (neuromotor.physics.reflex), its paths are grid axes too (lists or ranges):
    reflex_gain = [0.0, 100.0, 400.0]  # 1/s^2, spinal path
    reflex_delay = [0.0, 0.04]         # s; the history grows to the grid's longest delay (at most 1 s)
    # long_latency_gain = [...]; long_latency_delay = [...]   # the long-latency path

Reflex axes need a ``[reflex]`` table (the setting they vary; its other fields stay); each
run's twin has the same reflex (the twins are shared per distinct controller, reflex included).
The grid's reflex history holds its longest delay: ``reflex.max_delay`` is raised to it, so a
row equals a single run of the config with that reflex. sweep.csv then has the columns
:data:`REFLEX_COLUMNS`; a grid over reflex gain x delay at one gain setting and magnitude
also draws reflex_map.png (stable cells, recovery time, the boundary).

Ball-speed sweeps: when the config has a ``[ball]`` table, ``magnitudes`` are ball
speeds (m/s) and every run is a contact rollout (:mod:`neuromotor.studies.sweep.ball_speed`) of that ball at that
speed; its twin is the same gains with the ball never launched. A ball aimed at ``ball.target``
is re-aimed for every speed, so each row equals ``neuromotor simulate`` of the config with
``ball.speed`` set to the row's magnitude. ``bodies``, ``directions`` and ``starts`` do not
apply (the aim and launch time come from ``[ball]``), and the config may not also hold
``[[perturbation]]`` tables. The gains grid, ``chunk``, ``inner_batch``, ``output`` and
``fitted`` work as for pulses. The table gets ``kind = "ball"``, the peak contact impulse on
the character and the body that received it (:data:`BALL_COLUMNS`).

Sweeps on the ground: when the bodies touch a ground (``[sim] root = "free"``, ``[ground]``)
every run is a contact rollout on it (:mod:`.on_ground`), the postural loop included when
``[balance]`` is on, and each row also gets ``simulate``'s ground and balance metrics
(:data:`GROUND_METRICS`: falls, sway, ground forces). A base motion then moves the ground.

Modules: :mod:`.grid` (the batch of a grid), :mod:`.runner` (sharded execution),
:mod:`.ball_speed` (ball-speed sweeps), :mod:`.on_ground` (sweeps on the ground); the ``[sweep]`` table is parsed by
:func:`neuromotor.config.sweep_spec`, the CSV is written by :mod:`neuromotor.io.tables` and the
figures drawn by :mod:`neuromotor.viz.sweep_plots` (and :mod:`neuromotor.viz.reflex_plots`).
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
from collections.abc import Sequence

import jax

from neuromotor.config.parse import load_sweep_config, read_fitted, sweep_spec
from neuromotor.config.specs import CONTROLLERS, GainSetting, SweepSpec
from neuromotor.errors import ConfigError
from neuromotor.io import tables
from neuromotor.io.tables import read_csv
from neuromotor.physics.perturbation import PLATFORM_KINDS
from neuromotor.studies.gains import gains_for
from neuromotor.studies.sweep.ball_speed import BallBatch, BallRunOut, BallSweeper, run_ball_sweep
from neuromotor.studies.sweep.grid import (
    BALL_COLUMNS,
    COLUMNS,
    METRIC_KEYS,
    REFLEX_COLUMNS,
    RunBatch,
    RunOut,
    build_batch,
    gain_keys,
    with_reflex_columns,
)
from neuromotor.studies.sweep.on_ground import GROUND_METRICS, GroundSweeper, ground_row_metrics
from neuromotor.studies.sweep.runner import AXIS, Sweeper, SweepResult, device_mesh, run_sweep, sweep_batches
from neuromotor.viz.sweep_plots import plot_gains_map, plot_sweep, save_figure


def write_csv(rows: list[dict], path, columns: Sequence[str] = COLUMNS) -> pathlib.Path:
    """One row per run (``columns``: COLUMNS, or BALL_COLUMNS for a ball-speed sweep), written
    through a temporary file and renamed."""
    return tables.write_csv(rows, path, columns)


def simulate_grid(
    cfg,
    spec: SweepSpec,
    setup,
    *,
    devices=None,
    chunk=None,
    inner_batch=None,
    progress: bool = True,
    keep_curves: bool = False,
) -> SweepResult:
    """Every run of the grid of ``spec`` on the prepared ``setup`` of ``cfg``: force pulses, or
    (``spec.kind == "ball"``) ball speeds; ``chunk`` and ``inner_batch`` default to the spec's;
    ``keep_curves``: keep every run's deviation curve d(t)."""
    from neuromotor.studies.ball_hit import balls_at_speeds
    from neuromotor.studies.simulate import body_lookup

    if spec.kind == "ball" and setup.ground is not None:
        raise ConfigError(
            f"{cfg.source}: field 'ground.enabled': a ball-speed sweep does not simulate the bodies' ground "
            "contact yet (a pulse sweep and `neuromotor simulate` do); set [ground] enabled = false"
        )
    if (cfg.ball is not None) != (spec.kind == "ball") or (spec.kind == "ball" and cfg.perturbations):
        # A pulse sweep's rollouts have no contact, a ball sweep's twins no pulses: never half a config.
        raise ConfigError(
            f"{cfg.source}: field 'ball': a sweep varies either the ball's speed (a [ball] and no "
            "[[perturbation]]) or perturbation[0] (no [ball]), not both"
        )
    model = setup.model
    mesh = None if devices is None else device_mesh(devices)
    sizes = dict(chunk=chunk or spec.chunk, inner_batch=inner_batch or spec.inner_batch, mesh=mesh, metric=cfg.metric)
    if spec.kind == "ball":
        try:  # aim every speed first: a speed that cannot reach the target is a config error
            balls = balls_at_speeds(setup, spec.magnitudes)
        except ConfigError:
            raise
        except ValueError as e:
            raise ConfigError(f"{cfg.source}: field 'sweep.magnitudes': {e}") from None
        ball_sweeper = BallSweeper(model, setup.ref, setup.options, setup.ball, setup.pulses, **sizes)
        return run_ball_sweep(
            ball_sweeper, setup, spec.magnitudes, spec.gains, balls=balls, keep_curves=keep_curves, progress=progress
        )
    index = body_lookup(model, f"{cfg.source}: field 'sweep.bodies'", setup.character)  # names or segment keywords
    hit = cfg.perturbations[0]
    if hit.kind in PLATFORM_KINDS and spec.bodies:
        what = "a base motion" if hit.kind == "base" else "a tilt"
        raise ConfigError(f"{cfg.source}: field 'sweep.bodies': perturbation[0] is {what}, which pushes no body")
    for i, b in enumerate(spec.bodies or []):  # every row of the grid can act (the rule of prepare)
        index(b)
        setup.window.check(dataclasses.replace(hit, body=b), f"sweep.bodies[{i}]", "perturbation[0].start")
    for i, t in enumerate(spec.starts or []):
        setup.window.check(dataclasses.replace(hit, start=float(t)), "perturbation[0].body", f"sweep.starts[{i}]")
    extra = None
    if setup.ground is None:
        sweeper = Sweeper(model, setup.ref, setup.options, **sizes)
    else:  # contact rollouts on the ground, with simulate's ground and balance metrics per row
        sweeper = GroundSweeper(model, setup.ref, setup.options, setup.ground, **sizes)
        extra = functools.partial(ground_row_metrics, setup)
    return run_sweep(
        sweeper,
        setup.gains,
        setup.pulses,
        spec.runs(hit, cfg.perturbations[1:]),
        index,
        model.body_names,
        keep_curves=keep_curves,
        progress=progress,
        direction_of=setup.direction_of,
        extra=extra,
        pivot=setup.tilt_pivot,
    )


def _gains_map_title(cfg, spec: SweepSpec, name: str) -> str:
    if len(spec.magnitudes) == 1 and spec.kind == "ball":
        aim = f"at {cfg.ball.target}" if cfg.ball.target is not None else "thrown"
        return name + f": {spec.magnitudes[0]:g} m/s ball {aim}, launched at {cfg.ball.launch:g} s"
    if len(spec.magnitudes) == 1:
        hit = cfg.perturbations[0]
        return name + f": {hit.label(spec.magnitudes[0])} {hit.place} at {hit.start:g} s"
    return name


def table_columns(cfg, spec: SweepSpec) -> tuple[str, ...]:
    """sweep.csv's columns for a config: a ball sweep's or a pulse sweep's, with the ground and
    balance metrics on the ground (the assist's impulse when it is on) and the reflex's."""
    columns: tuple[str, ...] = BALL_COLUMNS if spec.kind == "ball" else COLUMNS
    if cfg.ground_on and spec.kind != "ball":  # after the recovery metrics
        i = columns.index(METRIC_KEYS[-1]) + 1
        assist = ("assist_impulse_Ns", "assist_impulse_pct") if cfg.balance_on and cfg.balance.assist else ()
        columns = (*columns[:i], *GROUND_METRICS, *assist, *columns[i:])
    return with_reflex_columns(columns) if cfg.reflex is not None else columns


def write_outputs(cfg, spec: SweepSpec, result: SweepResult, out: pathlib.Path, name: str) -> dict[str, pathlib.Path]:
    """sweep.csv (with the precision of its runs, ``[sim] dtype``, and the reflex columns when
    the config has a ``[reflex]``), sweep.png (several magnitudes), gains_map.png (ks and kd
    both vary, one reflex setting) and reflex_map.png (reflex gain and delay both vary, one
    gain setting and magnitude: :func:`neuromotor.viz.reflex_plots.plot_stability_map`)."""
    rows = [dict(r, dtype=str(cfg.dtype)) for r in result.rows]
    files = {"csv": write_csv(rows, out / "sweep.csv", (*table_columns(cfg, spec), "dtype"))}
    if len(spec.magnitudes) > 1:
        files["plot"] = plot_sweep(result.rows, out / "sweep.png", title=name)
    one_reflex = len(spec.reflexes or ()) <= 1
    if len({g.ks for g in spec.gains}) > 1 and len({g.kd for g in spec.gains}) > 1 and one_reflex:
        files["gains_map"] = plot_gains_map(
            result.rows, out / "gains_map.png", spec.fitted, title=_gains_map_title(cfg, spec, name)
        )
    reflexes = spec.reflexes or ()
    if (
        len({r.gain for r in reflexes}) > 1
        and len({r.delay for r in reflexes}) > 1
        and len(spec.gains) == 1
        and len(spec.runs(cfg.perturbations[0])) == len(reflexes)
    ):
        from neuromotor.studies.sweep.stability import classified, map_options
        from neuromotor.viz.reflex_plots import plot_stability_map

        files["reflex_map"] = plot_stability_map(
            classified(result.rows), out / "reflex_map.png", title=_gains_map_title(cfg, spec, name), **map_options(cfg)
        )
    return files


def sweep_from_config(
    path, output=None, *, devices=None, chunk=None, inner_batch=None, fitted=None, progress: bool = True
) -> tuple[SweepResult, dict[str, pathlib.Path]]:
    """Run the sweep of a config file; write ``sweep.csv``, ``sweep.png`` and, when ks and kd
    both vary, ``gains_map.png`` into ``output`` (default: the config's ``sweep.output``).
    A config with a ``[ball]`` table sweeps the ball speed (see the module docstring)."""
    from neuromotor.studies.simulate import prepare

    cfg, spec = load_sweep_config(path)
    out = pathlib.Path(output or spec.output or pathlib.Path("out") / "sweep" / pathlib.Path(path).stem)
    if fitted is not None:
        spec = dataclasses.replace(spec, fitted=read_fitted(fitted, "--fitted"))
    lead = jax.process_index() == 0  # with several processes, each computes its share, one writes
    result = simulate_grid(
        cfg, spec, prepare(cfg), devices=devices, chunk=chunk, inner_batch=inner_batch, progress=progress and lead
    )
    if not lead:
        return result, {}
    return result, write_outputs(cfg, spec, result, out, pathlib.Path(path).stem)


__all__ = [
    "AXIS",
    "BALL_COLUMNS",
    "BallBatch",
    "BallRunOut",
    "BallSweeper",
    "COLUMNS",
    "CONTROLLERS",
    "GROUND_METRICS",
    "GainSetting",
    "GroundSweeper",
    "METRIC_KEYS",
    "REFLEX_COLUMNS",
    "RunBatch",
    "RunOut",
    "SweepResult",
    "SweepSpec",
    "Sweeper",
    "build_batch",
    "device_mesh",
    "gain_keys",
    "gains_for",
    "load_sweep_config",
    "plot_gains_map",
    "plot_sweep",
    "read_csv",
    "read_fitted",
    "run_ball_sweep",
    "run_sweep",
    "save_figure",
    "simulate_grid",
    "sweep_batches",
    "sweep_from_config",
    "sweep_spec",
    "table_columns",
    "write_csv",
    "write_outputs",
]
