"""A calibration from a config file or a prepared setup: problem, target, weights, start; and
running it end to end (fit.json + fit.png)."""

from __future__ import annotations

import dataclasses
import math
import pathlib
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from neuromotor.config.specs import (
    BODY_TARGET_KINDS,
    FEATURE_NAMES,
    FIT_SOLVERS,
    LEAVE_ONE_OUT_MAX_CASES,
    LENGTH_UNITS,
    FitSpec,
    FitTargetSpec,
    SolverOptions,
    onset,
)
from neuromotor.errors import ConfigError
from neuromotor.io.tables import json_safe, write_json
from neuromotor.studies import metrics as mx
from neuromotor.studies.fit import parameters as fp
from neuromotor.studies.fit.driver import fit
from neuromotor.studies.fit.evaluate import ResponseEvaluator
from neuromotor.studies.fit.problem import MULTIPLE, FitProblem, Part, make_problem
from neuromotor.studies.fit.result import FitError, FitResult
from neuromotor.studies.fit.surrogate import exact_peak_acceleration

if TYPE_CHECKING:
    from neuromotor.studies.simulate import Setup


@dataclasses.dataclass
class Calibration:
    """A calibration ready to run: problem, target, weights, start and solver settings."""

    setup: Setup
    problem: FitProblem
    target: np.ndarray  # (m,) flat, as y(x)
    weights: np.ndarray  # (m,)
    x0: np.ndarray
    solver: str = "optimistix_lm"
    options: SolverOptions = dataclasses.field(default_factory=SolverOptions)
    jacobian: str = "forward"
    labels: tuple[str, ...] = ()  # one per plotted curve column
    target_file: str | None = None
    not_fitted: str = ""  # a BVH trial: its channels left out (joints the model does not simulate)
    converted: str = ""  # a BVH trial: its joints read in another Euler order than the clip's
    feature_table: list[dict] = dataclasses.field(default_factory=list)  # per case: name -> value/sd/source
    source: str = "<calibration>"
    # Per residual: the target's sd in the output's units (rad, m; a feature's sd), NaN where the
    # target is a single trial; None: no sd anywhere.
    sd: np.ndarray | None = None
    # Per target: label, kind, unit and scale (output unit -> unit), curve columns [c0, c1), files.
    blocks: tuple[dict, ...] = ()
    leave_one_out: bool = False  # report each case's prediction by a fit on the others

    def case_index(self) -> np.ndarray:
        """The case of every residual (y is case-major for every kind)."""
        return np.repeat(np.arange(self.problem.n_cases), self.target.size // self.problem.n_cases)

    def column_index(self) -> np.ndarray:
        """The curve column (trajectory targets) or feature (feature targets) of every residual."""
        per_case = self.target.size // self.problem.n_cases
        s = self.problem.spec
        width = len(s.features) if s.kind == "features" else per_case // self.time.size
        return np.tile(np.arange(width), self.target.size // width)

    def report_blocks(self) -> tuple[dict, ...]:
        """:attr:`blocks`, or one block for the whole output when none were given."""
        if self.blocks:
            return self.blocks
        s = self.problem.spec
        if s.kind == "features":
            return (
                {"label": "features", "kind": "features", "unit": None, "scale": None, "columns": (0, len(s.features))},
            )
        width = self.target.size // (self.problem.n_cases * self.time.size)
        unit, scale = ("deg", 180.0 / math.pi) if s.kind == "joint_angles" else ("m", 1.0)
        return ({"label": s.kind, "kind": s.kind, "unit": unit, "scale": scale, "columns": (0, width)},)

    def errors(self, y, which=None) -> list[dict]:
        """Per target: the RMS of ``y - target`` in the target's unit (``rms``) and, where the
        target has an sd (corridors, features), the RMS of the z-scores ``(y - target) / sd``
        (``rms_sd``), over the residuals ``which`` (a boolean mask; default all) that count
        (weight > 0)."""
        y = np.asarray(y, float)
        mask = np.ones(y.size, bool) if which is None else np.asarray(which, bool)
        mask = mask & (self.weights > 0)
        col = self.column_index()
        out = []
        for b in self.report_blocks():
            sel = mask & (col >= b["columns"][0]) & (col < b["columns"][1])
            diff = (y - self.target)[sel]
            row = {"target": b["label"], "unit": b["unit"], "n": int(sel.sum())}
            row["rms"] = None if b["scale"] is None or not diff.size else float(b["scale"] * np.sqrt(np.mean(diff**2)))
            sd = None if self.sd is None else self.sd[sel]
            if sd is not None and sd.size and np.all(np.isfinite(sd)):
                row["rms_sd"] = float(np.sqrt(np.mean((diff / sd) ** 2)))
            else:
                row["rms_sd"] = None
            out.append(row)
        return out

    @property
    def time(self) -> np.ndarray:
        s = self.problem.spec
        return np.asarray(self.problem.ref.time[s.i0 : s.i1])

    def target_curves(self) -> np.ndarray:
        """Trajectory targets shaped like the evaluator's curves (C, T, c)."""
        c, t = self.problem.n_cases, self.time.size
        return self.target.reshape(c, t, -1)


@dataclasses.dataclass
class TargetBlock:
    """One target on the model before the window is known: its part of the output, each case's
    clip-time span, and its values on a grid of clip times."""

    part: Part
    labels: tuple[str, ...]  # one per curve column
    spans: list[tuple[float, float]]  # per case, clip seconds
    on_grid: Callable  # times (T,) -> (values (C, T, w) in output units, sd (C, T, w) or None, weights (w,))
    info: dict  # label, kind, unit, scale, files (the report's block, without its columns)


def _trajectory_block(setup, table, quantity: str, names=None, weights=None, angle_unit: str = "rad", source=None):
    """A joint-angle or body-position table on the model (names, weights and case count checked);
    ``table`` may be a list of one-case tables, one per case (``files = [...]``). Returns the
    block and the tables as matched to the model (a list)."""
    from neuromotor.studies.targets import match_trial, resample

    per_case = isinstance(table, list)
    tables = [match_trial(tb, setup.character, setup.options.h) for tb in (table if per_case else [table])]
    model = setup.model
    src = source or setup.config.source
    known = model.dof_names if quantity == "joint_angles" else model.body_names
    what = "DOF" if quantity == "joint_angles" else "body"
    for tb in tables:
        unknown = [n for n in tb.names if n not in known]
        if unknown:
            raise ConfigError(
                f"{tb.source}: field 'names' has unknown {what} name(s) {unknown[:5]}; "
                f"the model's are e.g. {list(known[:4])}"
            )
    names = list(tables[0].names) if names is None else list(names)
    for i, n in enumerate(names):
        if n not in known:
            raise ConfigError(
                f"{src}: field 'fit.target.{'dofs' if what == 'DOF' else 'bodies'}[{i}]' is an "
                f"unknown {what} name {n!r}"
            )
        for tb in tables:
            if n not in tb.names:
                raise ConfigError(f"{tb.source}: column {n!r} is missing (named by {src} fit.target)")
    corridors = [tb.sd is not None for tb in tables]
    if any(corridors) and not all(corridors):
        bad = tables[corridors.index(False)]
        raise ConfigError(
            f"{bad.source}: has no .sd columns but {tables[corridors.index(True)].source} has "
            f"(a target's files are all corridors or all single trials)"
        )
    weights = dict(weights or {})
    for n, w in weights.items():
        if n not in names:
            raise ConfigError(f"{src}: field 'fit.target.weights.{n}' names a {what} that is not fitted")
        if not (isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0):
            raise ConfigError(f"{src}: field 'fit.target.weights.{n}' must be a number >= 0, got {w!r}")
    n_cases = sum(tb.values.shape[0] for tb in tables)
    if n_cases != len(setup.config.perturbations):
        raise ConfigError(
            f"{tables[0].source}: holds {n_cases} case(s) but {src} has "
            f"{len(setup.config.perturbations)} [[perturbation]] entries (one per case)"
        )
    w = np.array([float(weights.get(n, 1.0)) for n in names])
    if quantity == "body_positions":
        w = np.repeat(w, 3)
        labels = tuple(f"{n}.{a}" for n in names for a in "xyz")
    else:
        labels = tuple(names)

    def on_grid(times):
        vals, sds = [], []
        for tb in tables:
            pick = [tb.names.index(n) for n in names]
            v = resample(tb, times, "fit.window")[:, :, pick]  # (c, T, k[, 3])
            # A corridor weighs each sample by 1 / sd(t): the residual counts in standard deviations.
            sd = None if tb.sd is None else resample(dataclasses.replace(tb, values=tb.sd), times)[:, :, pick]
            if quantity == "joint_angles" and angle_unit == "deg" and not tb.radians:
                v = np.deg2rad(v)
                sd = None if sd is None else np.deg2rad(sd)
            flat = lambda a: a.reshape(a.shape[0], a.shape[1], -1)
            vals.append(flat(v))
            sds.append(None if sd is None else flat(sd))
        return np.concatenate(vals), None if sds[0] is None else np.concatenate(sds), w

    spans = [(float(tb.time[0]), float(tb.time[-1])) for tb in tables for _ in range(tb.values.shape[0])]
    unit, scale = ("deg", 180.0 / math.pi) if quantity == "joint_angles" else ("m", 1.0)
    part = Part(quantity, tuple(known.index(n) for n in names))
    info = {"label": quantity, "kind": quantity, "unit": unit, "scale": scale, "files": [tb.source for tb in tables]}
    return TargetBlock(part, labels, spans, on_grid, info), tables


def _assemble(setup, blocks: list[TargetBlock], window, parameters, axes=None, kind=None):
    """The problem over every block's part, and the flat target, weights and sd."""
    parts = tuple(b.part for b in blocks)
    kind = kind or (parts[0].kind if len(parts) == 1 else MULTIPLE)
    problem = make_problem(
        setup,
        kind,
        parts[0].columns if len(parts) == 1 else (),
        window,
        names=parameters,
        parts=parts if any(p.kind in BODY_TARGET_KINDS for p in parts) or len(parts) > 1 else (),
        axes=axes,
    )
    s = problem.spec
    times = np.asarray(setup.ref.time[s.i0 : s.i1])
    vals, sds, ws, infos, col = [], [], [], [], 0
    for b in blocks:
        v, sd, w = b.on_grid(times)
        vals.append(v)
        sds.append(np.full(v.shape, np.nan) if sd is None else sd)
        wfull = np.broadcast_to(w, v.shape)
        ws.append(wfull / sd if sd is not None else wfull)
        infos.append(dict(b.info, columns=(col, col + v.shape[-1])))
        col += v.shape[-1]
    cat = lambda a: np.concatenate(a, -1).reshape(-1)
    sd = cat(sds)
    labels = tuple(lab for b in blocks for lab in b.labels)
    return problem, cat(vals), np.array(cat(ws)), labels, (None if np.all(np.isnan(sd)) else sd), tuple(infos)


def trajectory_calibration(
    setup,
    table,
    quantity: str,
    names=None,
    weights=None,
    window=None,
    angle_unit: str = "rad",
    source: str | None = None,
    parameters=fp.DEFAULT,
) -> tuple:
    """Target and weights for a trajectory table (see :mod:`neuromotor.studies.targets`).

    Returns (problem, target, weights, labels). ``names``: the DOFs or bodies to fit (default:
    every column of the file); ``weights``: name -> weight (default 1).
    """
    block, _ = _trajectory_block(setup, table, quantity, names, weights, angle_unit, source)
    problem, target, w, labels, _, _ = _assemble(setup, [block], window, parameters)
    return problem, target, w, labels


def _body_index(setup, name: str, field: str) -> int:
    """A body of the model by name or segment keyword; unknown: a ConfigError naming the field."""
    from neuromotor.model.skeleton import keyword_body, unknown_body

    model = setup.model
    if name in model.body_names:
        return model.body_names.index(name)
    b = keyword_body(setup.character, name) if setup.character is not None else None
    if b is None:
        raise ConfigError(f"{setup.config.source}: field '{field}': {unknown_body(model, setup.character, name)}")
    return int(b)


def _body_block(setup, t: FitTargetSpec, series, where: str, slot: int) -> tuple[TargetBlock, list]:
    """A ``body_angle`` / ``body_position`` target on the model: the part, each case's clip-time
    span (file time 0 at ``time_offset``, default the case's onset) and its world axis at onset."""
    from neuromotor.model.facing import resolve_direction

    cfg, model = setup.config, setup.model
    b = _body_index(setup, t.body, f"{where}.body")
    other = -1 if t.relative_to == "world" else _body_index(setup, t.relative_to, f"{where}.relative_to")
    if other == b:
        raise ConfigError(
            f"{cfg.source}: field '{where}.relative_to' = {t.relative_to!r} is the body itself ({t.body!r})"
        )
    lever = (0.0, 0.0, 0.0)
    if t.point is not None:
        x, y, z = (float(v) for v in np.asarray(t.point, float) - np.asarray(model.com[b], float))
        lever = (x, y, z)
    onsets = [onset([p]) for p in cfg.perturbations]
    offsets = [o if t.time_offset is None else float(t.time_offset) for o in onsets]
    frame_at = onsets if cfg.still is None else [float(cfg.still)] * len(onsets)  # a held pose: its frame
    axes = [resolve_direction(t.axis, setup.character, o, f"{cfg.source}: field '{where}.axis'") for o in frame_at]
    spans = [(off + float(s.time[0]), off + float(s.time[-1])) for off, s in zip(offsets, series)]
    if t.kind == "body_angle":
        unit, to_si = t.angle_unit, (math.pi / 180.0 if t.angle_unit == "deg" else 1.0)
    else:
        unit, to_si = t.length_unit, LENGTH_UNITS[t.length_unit]
    corridor = series[0].sd is not None

    def on_grid(times):
        vals, sds = [], []
        for c, (s, off) in enumerate(zip(series, offsets)):
            clip = off + s.time
            lo, hi = float(times[0]), float(times[-1])
            if lo < clip[0] - 1e-9 or hi > clip[-1] + 1e-9:
                raise ConfigError(
                    f"{s.source}: field 'fit.window' [{lo:.4f}, {hi:.4f}] s is outside the target's time span "
                    f"[{clip[0]:.4f}, {clip[-1]:.4f}] s (clip time; the file's time 0 is at {off:g} s, case {c})"
                )
            vals.append(np.interp(times, clip, s.value) * to_si)
            if corridor:
                sds.append(np.interp(times, clip, s.sd) * to_si)
        v = np.stack(vals)[:, :, None]
        return v, (np.stack(sds)[:, :, None] if corridor else None), np.array([t.weight])

    files = sorted({s.source for s in series}, key=[s.source for s in series].index)
    info = {"label": t.label, "kind": t.kind, "unit": unit, "scale": 1.0 / to_si, "files": files, "corridor": corridor}
    part = Part(t.kind, body=b, other=other, lever=lever, slot=slot)
    return TargetBlock(part, (t.label,), spans, on_grid, info), axes


def _default_window(setup, blocks: list[TargetBlock]) -> tuple[float, float]:
    """The part of the simulation every target covers (every case)."""
    sim_time = np.asarray(setup.ref.time[: setup.options.n_steps + 1])
    lo = max([float(sim_time[0])] + [sp[0] for b in blocks for sp in b.spans])
    hi = min([float(sim_time[-1])] + [sp[1] for b in blocks for sp in b.spans])
    if not hi - lo >= setup.options.h - 1e-9:
        spans = "; ".join(f"{b.info['files'][0]}: {[list(np.round(sp, 4)) for sp in b.spans]}" for b in blocks)
        raise ConfigError(
            f"{setup.config.source}: field 'fit.window': no part of the simulated span "
            f"[{sim_time[0]:.4f}, {sim_time[-1]:.4f}] s is covered by every target (clip-time spans {spans}); "
            f"check the time_unit and time_offset"
        )
    return lo, hi


def load_calibration(path, solver: str | None = None, character=None, traj=None) -> Calibration:
    """Read a fit config (TOML; layout in docs/fitting.md) into a :class:`Calibration`."""
    from neuromotor.config.fields import read_toml

    path = pathlib.Path(path)
    return calibration_from_dict(read_toml(path), str(path), path.parent, solver, character, traj)


def calibration_from_dict(
    data: dict, source: str = "<dict>", base_dir=None, solver: str | None = None, character=None, traj=None
) -> Calibration:
    """A :class:`Calibration` from a config's table (``[fit]`` parsed by :func:`neuromotor.config.fit_spec`)."""
    from neuromotor.config.parse import fit_spec, simulation_config

    cfg = simulation_config(data, source, base_dir)
    spec = fit_spec(data, cfg, base_dir)
    return calibration_from_spec(cfg, spec, solver, character, traj)


def calibration_from_spec(cfg, spec: FitSpec, solver: str | None = None, character=None, traj=None) -> Calibration:
    """The calibration of a parsed config: the fit starts from the config's gains."""
    from neuromotor.studies.simulate import prepare
    from neuromotor.studies.targets import read_series, read_target

    if solver is not None and solver not in FIT_SOLVERS:
        raise ConfigError(f"unknown solver {solver!r}; choose one of {', '.join(FIT_SOLVERS)}")
    if any(n in ("ks", "kd") for n in spec.parameters) and not (cfg.ks > 0 and cfg.kd > 0):
        raise ConfigError(f"{cfg.source}: field 'gains.ks'/'gains.kd' (the starting gains) must be > 0")
    common = dict(solver=solver or spec.solver, options=spec.options, jacobian=spec.jacobian, source=cfg.source)
    n_cases = len(cfg.perturbations)
    loo = spec.leave_one_out if spec.leave_one_out is not None else 2 <= n_cases <= LEAVE_ONE_OUT_MAX_CASES
    common["leave_one_out"] = bool(loo) and n_cases >= 2
    if spec.target.kind == "features":
        setup = prepare(cfg, character, traj)
        return _feature_calibration(setup, spec, common)
    # Every file is read before the (slow) inverse dynamics: bad files fail fast.
    read: list = []
    for t in spec.targets:
        if t.kind in BODY_TARGET_KINDS:
            read.append(read_series(t.paths, t.time_unit, t.column, n_cases))
            continue
        tables = []
        for path in t.paths:
            table = read_target(path, t.kind, t.time_offset or 0.0)
            if t.files and table.values.shape[0] != 1:
                raise ConfigError(f"{path}: holds {table.values.shape[0]} cases; each of files = [...] gives one case")
            if table.bvh is not None:  # a recorded trial: checked against the clip before the inverse dynamics too
                from neuromotor.studies.simulate import config_character
                from neuromotor.studies.targets import match_trial

                if character is None:
                    character, traj = config_character(cfg)
                table = match_trial(table, character, cfg.h)
            tables.append(table)
        read.append(tables if t.files else tables[0])
    setup = prepare(cfg, character, traj)
    blocks: list[TargetBlock] = []
    axes: list[list[np.ndarray]] = []
    matched: list = []
    many = len(spec.targets) > 1
    for i, (t, data) in enumerate(zip(spec.targets, read)):
        where = f"fit.target[{i}]" if many else "fit.target"
        if t.kind in BODY_TARGET_KINDS:
            block, resolved = _body_block(setup, t, data, where, len(axes))
            axes.append(resolved)
        else:
            block, data = _trajectory_block(setup, data, t.kind, t.names or None, t.weights, t.angle_unit, cfg.source)
            block.info["label"] = t.kind if not many else f"{t.kind} ({t.paths[0].name})"
            matched += data
        blocks.append(block)
    window = spec.window
    if window is None and axes:
        window = _default_window(setup, blocks)
    case_axes = np.stack([np.stack(a) for a in axes], 1) if axes else None  # (C, K, 3)
    problem, target, w, labels, sd, infos = _assemble(setup, blocks, window, spec.parameters, case_axes)
    common["x0"] = fp.start(setup.gains, problem.names, cfg.source)
    return Calibration(
        setup=setup,
        problem=problem,
        target=target,
        weights=w,
        labels=labels,
        target_file=", ".join(str(p) for t in spec.targets for p in t.paths),
        not_fitted="; ".join(dict.fromkeys(tb.not_fitted for tb in matched if tb.not_fitted)),
        converted="; ".join(dict.fromkeys(tb.converted for tb in matched if tb.converted)),
        sd=sd,
        blocks=infos,
        **common,
    )


def _feature_calibration(setup, spec: FitSpec, common: dict) -> Calibration:
    """Feature targets: one residual per listed feature of each case, weighted by 1/sd."""
    model, t = setup.model, spec.target
    for i, n in enumerate(t.names):
        if n not in model.dof_names:
            raise ConfigError(
                f"{setup.config.source}: field 'fit.target.dofs[{i}]' is an unknown DOF name {n!r} "
                f"(e.g. {list(model.dof_names[:3])})"
            )
    table = [{name: f.as_dict() for name, f in row.items()} for row in t.cases]
    feats = tuple(n for n in FEATURE_NAMES if any(n in row for row in table))
    problem = make_problem(
        setup,
        "features",
        [model.dof_names.index(n) for n in t.names],
        spec.window,
        feats,
        names=spec.parameters,
        **dataclasses.asdict(t.surrogate),
    )
    common = dict(common, x0=fp.start(setup.gains, problem.names, setup.config.source))
    target = np.array([row.get(n, {}).get("value", 0.0) for row in table for n in feats])
    # A feature a case does not list gets weight 0: it is computed but does not count.
    w = np.array([1.0 / row[n]["sd"] if n in row else 0.0 for row in table for n in feats])
    sd = np.array([row[n]["sd"] if n in row else np.nan for row in table for n in feats])
    return Calibration(
        setup=setup,
        problem=problem,
        target=target,
        weights=w,
        labels=("deviation (deg)",),
        feature_table=table,
        sd=sd,
        **common,
    )


def calibrate(
    cal: Calibration,
    outdir=None,
    progress: bool = True,
    evaluator: ResponseEvaluator | None = None,
    strict: bool = False,
) -> tuple[FitResult, dict]:
    """Fit, then write ``fit.json`` and ``fit.png`` to ``outdir`` (if given).

    Returns the result and the JSON document (which adds the problem description and, for
    feature targets, the surrogate and exact features at the fitted gains).
    """
    ev = evaluator or ResponseEvaluator(cal.problem, cal.jacobian)
    res = fit(ev, cal.target, cal.weights, cal.x0, cal.solver, cal.options, progress=progress, strict=False)
    doc = {
        "config": cal.source,
        "target_file": cal.target_file,
        "target_kind": cal.problem.spec.kind,
        "window_s": [float(cal.time[0]), float(cal.time[-1])],
        "h": cal.setup.options.h,
        "cases": [dict(p) for p in cal.setup.config.perturbations],
        **res.to_json(),
    }
    if cal.blocks:
        doc["targets"] = [{k: v for k, v in b.items() if k != "scale"} for b in cal.blocks]
    if cal.not_fitted:
        doc["not_fitted"] = cal.not_fitted
    if cal.converted:
        doc["euler_orders_converted"] = cal.converted
    if cal.problem.spec.kind == "features":
        doc["features"] = _feature_report(cal, ev, res)
    fitted_y = ev(res.x).y
    case = cal.case_index()
    doc["case_errors"] = [{"case": c, "fitted": cal.errors(fitted_y, case == c)} for c in range(cal.problem.n_cases)]
    if cal.leave_one_out and res.converged:
        doc["leave_one_out"] = leave_one_out(cal, ev, res.x, progress=progress)
    doc = json_safe(doc)  # NaN/inf (e.g. an exact recovery time that never came) -> null
    if outdir is not None:
        outdir = pathlib.Path(outdir)
        from neuromotor.viz.fit_plots import plot_fit

        write_json(outdir / "fit.json", doc)
        from neuromotor.config.specs import PARAMETER_UNITS

        plot_fit(cal, ev(cal.x0), ev(res.x), outdir / "fit.png", res, units=PARAMETER_UNITS)
    if strict and not res.converged:
        raise FitError(f"fit with {res.solver} failed ({res.status}): {res.message}", res)
    return res, doc


def leave_one_out(cal: Calibration, ev: ResponseEvaluator, x_start, progress: bool = False) -> list[dict]:
    """Each case predicted by a fit on the others: the fit of ``cal`` with that case's residuals
    weighted 0 (the same minimizer as a fit of the other cases alone: the cases are independent
    rollouts of one batch, so no new compile), from ``x_start`` (the fit on all cases), then that
    case's errors (:meth:`Calibration.errors`) at the values found."""
    case = cal.case_index()
    out = []
    for c in range(cal.problem.n_cases):
        w = np.where(case == c, 0.0, cal.weights)
        r = fit(ev, cal.target, w, x_start, cal.solver, cal.options, progress=progress, strict=False)
        out.append(
            {
                "case": c,
                "status": r.status,
                "iterations": r.iterations,
                "values": r.values,
                "predicted": cal.errors(ev(r.x).y, case == c),
            }
        )
    return out


def _feature_report(cal: Calibration, ev: ResponseEvaluator, res: FitResult) -> list[dict]:
    s = cal.problem.spec
    fitted = ev(res.x)
    y = fitted.y.reshape(cal.problem.n_cases, len(s.features))
    out = []
    for c, row in enumerate(cal.feature_table):
        dev = fitted.curves[c, :, 0]
        start = float(cal.problem.start[c])
        exact = mx.recovery_metrics(cal.time, dev, start, s.fraction, s.floor_deg)
        exact_named = {
            "peak_deviation_deg": exact["peak_deviation_deg"],
            "time_to_peak_s": exact["time_of_peak_s"] - start,
            "recovery_time_s": exact["recovery_time_s"],
            "overshoot_deg": exact["overshoot_deg"],
            "peak_acceleration_deg_s2": exact_peak_acceleration(fitted.curves[c, :, 1]),
        }
        out.append(
            {
                n: {
                    "target": row.get(n, {}).get("value"),
                    "sd": row.get(n, {}).get("sd"),
                    "source": row.get(n, {}).get("source"),
                    "fitted_surrogate": float(y[c, j]),
                    "fitted_exact": exact_named[n],
                }
                for j, n in enumerate(s.features)
            }
        )
    return out
