"""Studies of the delayed stretch reflex (:mod:`neuromotor.physics.reflex`, docs/reflex.md).

* :func:`compare_paths`: one hit under the paper's muscle feedback alone, with the spinal reflex
  added, and with the long-latency path too; each run's deviation d(t) against its own
  unperturbed twin and its recovery metrics (:mod:`neuromotor.studies.metrics`).
* :func:`stability_grid` / :func:`stability_from_config`: the paper's stability argument
  (Section 3) made measurable: the hit over a grid of delayed feedback gain x loop delay with the
  sweep machinery (:mod:`neuromotor.studies.sweep`, reflex axes), each cell classified by
  :func:`classify`.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any

import numpy as np

from neuromotor.config.parse import load_simulation_config, load_sweep_config
from neuromotor.config.specs import GainSetting, ReflexSpec, SimulationConfig, SweepSpec, reflex_grid
from neuromotor.errors import ConfigError
from neuromotor.io import tables
from neuromotor.studies.simulate import deviation_curve, prepare, run
from neuromotor.studies.sweep import COLUMNS, simulate_grid
from neuromotor.studies.sweep.grid import with_reflex_columns
from neuromotor.studies.sweep.stability import (  # noqa: F401
    DECAY_FRACTION,
    PAPER_FEEDBACK,
    STABLE_PEAK_DEG,
    classified,
    classify,
    map_options,
)

METRICS = (
    "peak_deviation_deg",
    "time_to_peak_s",
    "recovery_time_s",
    "overshoot_deg",
    "final_error_deg",
    "unperturbed_rms_error_deg",
    "peak_reflex_Nm",
    "diverged",
)
PATH_NAMES = ("muscle feedback only", "+ spinal reflex", "+ spinal and long-latency")


# ----------------------------------------------------------------------------- feedback paths


@dataclasses.dataclass
class PathComparison:
    time: np.ndarray  # (S+1,) clip time
    curves: dict[str, np.ndarray]  # name -> d(t) (deg) against the run's own twin
    metrics: dict[str, dict]  # name -> METRICS
    hit_start: float  # s, clip time
    configs: dict[str, SimulationConfig]


def path_configs(cfg: SimulationConfig) -> dict[str, SimulationConfig]:
    """The three controllers of :data:`PATH_NAMES`: no reflex; the config's ``[reflex]`` with the
    long-latency path off; the config's ``[reflex]`` as given (defaults: :class:`ReflexSpec`)."""
    rx = cfg.reflex or ReflexSpec()
    spinal = dataclasses.replace(rx, long_latency_gain=0.0)
    return dict(
        zip(
            PATH_NAMES,
            (
                dataclasses.replace(cfg, reflex=None),
                dataclasses.replace(cfg, reflex=spinal),
                dataclasses.replace(cfg, reflex=rx),
            ),
        )
    )


def compare_paths(cfg: SimulationConfig, character=None, traj=None) -> PathComparison:
    """Perturbed and unperturbed runs of ``cfg``'s hit under each of :func:`path_configs`."""
    if not cfg.perturbations:
        raise ConfigError(f"{cfg.source}: field 'perturbation' is required: the hit to compare the paths on")
    start = min(p.start for p in cfg.perturbations)
    curves, table, configs = {}, {}, path_configs(cfg)
    time = None
    for name, c in configs.items():
        setup = prepare(c, character, traj)
        character, traj = setup.character, setup.traj  # load the clip once
        r = run(setup, check=False)
        time = np.asarray(r.perturbed.time)
        curves[name] = deviation_curve(setup, r.perturbed, r.unperturbed)
        m = r.metrics
        reflex = 0.0 if r.perturbed.reflex is None else float(np.max(np.abs(np.asarray(r.perturbed.reflex))))
        table[name] = {
            **{
                k: m[k]
                for k in (
                    "peak_deviation_deg",
                    "time_of_peak_s",
                    "recovery_time_s",
                    "overshoot_deg",
                    "final_error_deg",
                    "unperturbed_rms_error_deg",
                )
            },
            "time_to_peak_s": m["time_of_peak_s"] - start,
            "peak_reflex_Nm": reflex,
            "diverged": bool(m["diverged"]),
        }
    assert time is not None  # path_configs gives three configs
    return PathComparison(time, curves, table, start, configs)


def _path_label(name: str, cfg: SimulationConfig) -> str:
    rx = cfg.reflex
    if rx is None:
        return f"{name} (ks={cfg.ks:g}, kd={cfg.kd:g})"
    text = f"{name} ({rx.gain:g}/s$^2$ at {1000 * rx.delay:g} ms"
    if rx.long_latency_gain:
        text += f"; {rx.long_latency_gain:g}/s$^2$ at {1000 * rx.long_latency_delay:g} ms"
    return text + ")"


def paths_from_config(path, output, figure=None) -> tuple[PathComparison, dict[str, pathlib.Path]]:
    """:func:`compare_paths` of a config file: ``paths.csv`` and ``paths.json`` (the metrics
    side by side), ``paths.png`` (the d(t) curves) in ``output``; the figure also to ``figure``."""
    from neuromotor.viz.reflex_plots import plot_deviation_paths

    cfg = load_simulation_config(path)
    comp = compare_paths(cfg)
    out = pathlib.Path(output)
    rows = [dict(path=name, **comp.metrics[name]) for name in comp.curves]
    files = {
        "csv": tables.write_csv(rows, out / "paths.csv", ("path", *METRICS)),
        "json": tables.write_json(out / "paths.json", tables.json_safe({"hit_start_s": comp.hit_start, "runs": rows})),
    }
    labels = {_path_label(n, comp.configs[n]): n for n in comp.curves}
    curves = {label: comp.curves[n] for label, n in labels.items()}
    metrics = {label: comp.metrics[n] for label, n in labels.items()}
    hit = cfg.perturbations[0]
    title = f"{hit.label()} {hit.place} at {hit.start:g} s"
    for key, target in (("plot", out / "paths.png"), ("figure", figure)):
        if target is not None:
            files[key] = plot_deviation_paths(comp.time, curves, target, comp.hit_start, title, metrics)
    return comp, files


# ----------------------------------------------------------------------------- stability


def stability_grid(
    cfg: SimulationConfig,
    gains,
    delays,
    *,
    setup=None,
    chunk: int = 64,
    inner_batch: int = 1,
    bound_deg: float = STABLE_PEAK_DEG,
    progress: bool = False,
) -> list[dict]:
    """The hit of ``cfg`` (perturbation[0]) at every spinal reflex gain (1/s^2) x delay (s) over
    the config's ``[reflex]`` (default :class:`ReflexSpec`), muscle feedback at ``cfg``'s gains;
    one classified row per cell, gain outermost."""
    cfg = cfg if cfg.reflex is not None else dataclasses.replace(cfg, reflex=ReflexSpec())
    assert cfg.reflex is not None
    spec = SweepSpec(
        [float(cfg.perturbations[0].magnitude or 0.0)],
        [cfg.gains],
        chunk=chunk,
        inner_batch=inner_batch,
        reflexes=reflex_grid(cfg.reflex, reflex_gain=list(gains), reflex_delay=list(delays)),
    )
    result = simulate_grid(cfg, spec, setup or prepare(cfg), progress=progress)
    return classified(result.rows, bound_deg)


def implicit_reference(
    cfg: SimulationConfig,
    gains,
    *,
    setup=None,
    chunk: int = 64,
    inner_batch: int = 1,
    bound_deg: float = STABLE_PEAK_DEG,
    progress: bool = False,
) -> list[dict]:
    """The same extra feedback without delay, inside K and D of Eq. 2 (implicit, like the muscle
    feedback): for every gain g the muscle gains ``(ks + g, kd + g c)`` and no reflex, which is
    what a reflex of gain g and rate weight c at zero delay adds, evaluated explicitly
    (:mod:`neuromotor.physics.reflex`). One classified row per gain (key ``reflex_gain``)."""
    c = (cfg.reflex or ReflexSpec()).rate_weight
    base = dataclasses.replace(cfg, reflex=None)
    settings = [GainSetting(cfg.ks + g, cfg.kd + g * c, label=f"implicit +{g:g}") for g in gains]
    spec = SweepSpec([float(cfg.perturbations[0].magnitude or 0.0)], settings, chunk=chunk, inner_batch=inner_batch)
    rows = simulate_grid(base, spec, setup or prepare(base), progress=progress).rows
    return [
        dict(
            r,
            reflex_gain=float(g),
            reflex_delay=0.0,
            long_latency_gain=0.0,
            long_latency_delay=0.0,
            feedback="implicit",
        )
        for r, g in zip(classified(rows, bound_deg), gains)
    ]


def stability_boundary(rows: list[dict]) -> list[dict]:
    """Per delay: the largest gain whose cell is stable together with every smaller gain's, and
    the smallest unstable gain (None: none)."""
    out = []
    for d in sorted({r["reflex_delay"] for r in rows}):
        cells = sorted((r for r in rows if r["reflex_delay"] == d), key=lambda r: r["reflex_gain"])
        bad = [r["reflex_gain"] for r in cells if r["stability"] != "stable"]
        ok = [r["reflex_gain"] for r in cells if r["stability"] == "stable" and (not bad or r["reflex_gain"] < bad[0])]
        out.append(
            {
                "delay_s": d,
                "largest_stable_gain": max(ok) if ok else None,
                "smallest_unstable_gain": bad[0] if bad else None,
            }
        )
    return out


def stability_from_config(
    path, output, figure=None, *, bound_deg: float = STABLE_PEAK_DEG, inner_batch=None, progress: bool = True
) -> tuple[list[dict], dict[str, pathlib.Path]]:
    """The stability map of a sweep config whose ``[sweep]`` varies ``reflex_gain`` and
    ``reflex_delay`` (one gain setting, one magnitude), with the :func:`implicit_reference` row:
    ``stability.csv`` (every cell classified, column ``feedback``: delayed or implicit),
    ``boundary.json`` and ``stability.png`` in ``output`` (the figure also to ``figure``)."""
    from neuromotor.viz.reflex_plots import plot_stability_map

    cfg, spec = load_sweep_config(path)
    out_dir = output or spec.output
    if not out_dir:
        raise ConfigError(f"{cfg.source}: field 'sweep.output' is needed when no output folder is given")
    rx = spec.reflexes or ()
    one_setting = len(spec.runs(cfg.perturbations[0])) == len(rx)  # one gain setting, one magnitude
    if len({r.gain for r in rx}) < 2 or len({r.delay for r in rx}) < 2 or not one_setting:
        raise ConfigError(
            f"{cfg.source}: field 'sweep': the stability map needs reflex_gain and reflex_delay lists "
            "of two or more values each, one gain setting and one magnitude"
        )
    setup = prepare(cfg)
    sizes: dict[str, Any] = dict(
        chunk=spec.chunk, inner_batch=inner_batch or spec.inner_batch, bound_deg=bound_deg, progress=progress
    )
    result = simulate_grid(cfg, spec, setup, inner_batch=sizes["inner_batch"], progress=progress)
    rows = [dict(r, feedback="delayed") for r in classified(result.rows, bound_deg)]
    implicit = implicit_reference(cfg, sorted({r.gain for r in rx}), **sizes)
    out = pathlib.Path(out_dir)
    boundary = stability_boundary(rows)
    columns = (*with_reflex_columns(COLUMNS), "feedback", "stability")
    files = {
        "csv": tables.write_csv(rows + implicit, out / "stability.csv", columns),
        "json": tables.write_json(
            out / "boundary.json",
            tables.json_safe(
                {
                    "bound_deg": bound_deg,
                    "muscle_ks": cfg.ks,
                    "muscle_kd": cfg.kd,
                    "boundary": boundary,
                    "implicit_unstable_gains": [r["reflex_gain"] for r in implicit if r["stability"] != "stable"],
                }
            ),
        ),
    }
    hit = cfg.perturbations[0]
    assert cfg.reflex is not None  # the config's reflex axes need a [reflex] table (config.parse)
    title = (
        f"{hit.label()} {hit.place} at {hit.start:g} s; muscle feedback ks={cfg.ks:g}, "
        f"kd={cfg.kd:g} beside the delayed path (rate weight {cfg.reflex.rate_weight:g} s)"
    )
    for key, target in (("plot", out / "stability.png"), ("figure", figure)):
        if target is not None:
            files[key] = plot_stability_map(rows, target, implicit=implicit, title=title, **map_options(cfg, bound_deg))
    return rows + implicit, files
