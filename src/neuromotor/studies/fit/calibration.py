"""A calibration from a config file or a prepared setup: problem, target, weights, start; and
running it end to end (fit.json + fit.png)."""

from __future__ import annotations

import dataclasses
import math
import pathlib
from typing import TYPE_CHECKING

import numpy as np

from neuromotor.config.specs import FEATURE_NAMES, FIT_SOLVERS, FitSpec, SolverOptions
from neuromotor.errors import ConfigError
from neuromotor.io.tables import json_safe, write_json
from neuromotor.studies import metrics as mx
from neuromotor.studies.fit import parameters as fp
from neuromotor.studies.fit.driver import fit
from neuromotor.studies.fit.evaluate import ResponseEvaluator
from neuromotor.studies.fit.problem import FitProblem, make_problem
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

    @property
    def time(self) -> np.ndarray:
        s = self.problem.spec
        return np.asarray(self.problem.ref.time[s.i0 : s.i1])

    def target_curves(self) -> np.ndarray:
        """Trajectory targets shaped like the evaluator's curves (C, T, c)."""
        c, t = self.problem.n_cases, self.time.size
        return self.target.reshape(c, t, -1)


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
    from neuromotor.studies.targets import match_trial, resample

    table = match_trial(table, setup.character, setup.options.h)  # a BVH trial: the simulated DOFs only
    model = setup.model
    src = source or setup.config.source
    known = model.dof_names if quantity == "joint_angles" else model.body_names
    what = "DOF" if quantity == "joint_angles" else "body"
    unknown = [n for n in table.names if n not in known]
    if unknown:
        raise ConfigError(
            f"{table.source}: field 'names' has unknown {what} name(s) {unknown[:5]}; "
            f"the model's are e.g. {list(known[:4])}"
        )
    names = list(table.names) if names is None else list(names)
    for i, n in enumerate(names):
        if n not in known:
            raise ConfigError(
                f"{src}: field 'fit.target.{'dofs' if what == 'DOF' else 'bodies'}[{i}]' is an "
                f"unknown {what} name {n!r}"
            )
        if n not in table.names:
            raise ConfigError(f"{table.source}: column {n!r} is missing (named by {src} fit.target)")
    weights = dict(weights or {})
    for n, w in weights.items():
        if n not in names:
            raise ConfigError(f"{src}: field 'fit.target.weights.{n}' names a {what} that is not fitted")
        if not (isinstance(w, (int, float)) and not isinstance(w, bool) and math.isfinite(w) and w >= 0):
            raise ConfigError(f"{src}: field 'fit.target.weights.{n}' must be a number >= 0, got {w!r}")
    if table.values.shape[0] != len(setup.config.perturbations):
        raise ConfigError(
            f"{table.source}: holds {table.values.shape[0]} case(s) but {src} has "
            f"{len(setup.config.perturbations)} [[perturbation]] entries (one per case)"
        )
    columns = [known.index(n) for n in names]
    problem = make_problem(setup, quantity, columns, window, names=parameters)
    s = problem.spec
    times = np.asarray(setup.ref.time[s.i0 : s.i1])
    vals = resample(table, times, "fit.window")  # (C, T, k[, 3])
    pick = [table.names.index(n) for n in names]
    vals = vals[:, :, pick]
    # A corridor weighs each sample by 1 / sd(t): the residual counts in standard deviations.
    sd = None if table.sd is None else resample(dataclasses.replace(table, values=table.sd), times)[:, :, pick]
    if quantity == "joint_angles" and angle_unit == "deg" and not table.radians:
        vals = np.deg2rad(vals)
        sd = None if sd is None else np.deg2rad(sd)
    w = np.array([float(weights.get(n, 1.0)) for n in names])
    if quantity == "body_positions":
        w = np.repeat(w, 3)
        labels = tuple(f"{n}.{a}" for n in names for a in "xyz")
    else:
        labels = tuple(names)
    wfull = np.broadcast_to(w, vals.reshape(vals.shape[0], vals.shape[1], -1).shape).reshape(-1)
    if sd is not None:
        wfull = wfull / sd.reshape(-1)
    return problem, vals.reshape(-1), np.array(wfull), labels


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
    from neuromotor.studies.targets import read_target

    if solver is not None and solver not in FIT_SOLVERS:
        raise ConfigError(f"unknown solver {solver!r}; choose one of {', '.join(FIT_SOLVERS)}")
    if any(n in ("ks", "kd") for n in spec.parameters) and not (cfg.ks > 0 and cfg.kd > 0):
        raise ConfigError(f"{cfg.source}: field 'gains.ks'/'gains.kd' (the starting gains) must be > 0")
    common = dict(solver=solver or spec.solver, options=spec.options, jacobian=spec.jacobian, source=cfg.source)
    t = spec.target
    if t.kind == "features":
        setup = prepare(cfg, character, traj)
        return _feature_calibration(setup, spec, common)
    table = read_target(t.file, t.kind, t.time_offset)  # before the (slow) inverse dynamics: bad files fail fast
    if table.bvh is not None:  # a recorded trial: checked against the clip before the inverse dynamics too
        from neuromotor.studies.simulate import load_character
        from neuromotor.studies.targets import match_trial

        if character is None:
            character, traj = load_character(cfg.clip, cfg.units, cfg.up_axis, cfg.stature, cfg.mass_options())
        table = match_trial(table, character, cfg.h)
    setup = prepare(cfg, character, traj)
    problem, target, w, labels = trajectory_calibration(
        setup, table, t.kind, t.names or None, t.weights, spec.window, t.angle_unit, cfg.source, spec.parameters
    )
    common["x0"] = fp.start(setup.gains, problem.names, cfg.source)
    return Calibration(
        setup=setup,
        problem=problem,
        target=target,
        weights=w,
        labels=labels,
        target_file=str(t.file),
        not_fitted=table.not_fitted,
        converted=table.converted,
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
    return Calibration(
        setup=setup,
        problem=problem,
        target=target,
        weights=w,
        labels=("deviation (deg)",),
        feature_table=table,
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
    if cal.not_fitted:
        doc["not_fitted"] = cal.not_fitted
    if cal.converted:
        doc["euler_orders_converted"] = cal.converted
    if cal.problem.spec.kind == "features":
        doc["features"] = _feature_report(cal, ev, res)
    doc = json_safe(doc)  # NaN/inf (e.g. an exact recovery time that never came) -> null
    if outdir is not None:
        outdir = pathlib.Path(outdir)
        from neuromotor.viz.fit_plots import plot_fit

        write_json(outdir / "fit.json", doc)
        plot_fit(cal, ev(cal.x0), ev(res.x), outdir / "fit.png", res)
    if strict and not res.converged:
        raise FitError(f"fit with {res.solver} failed ({res.status}): {res.message}", res)
    return res, doc


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
