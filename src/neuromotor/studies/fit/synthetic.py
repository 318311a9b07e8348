"""Synthetic targets: the model's own output at known gains, plus seeded noise."""

from __future__ import annotations

import pathlib

import numpy as np

from neuromotor.errors import ConfigError
from neuromotor.studies.fit.calibration import Calibration
from neuromotor.studies.fit.evaluate import ResponseEvaluator
from neuromotor.studies.fit.parameters import UNITS, beyond_history, describe
from neuromotor.studies.fit.problem import make_problem
from neuromotor.studies.fit.result import FitError


def synthetic_target(
    cal: Calibration,
    ks: float | None = None,
    kd: float | None = None,
    noise: float = 0.0,
    seed: int = 0,
    evaluator: ResponseEvaluator | None = None,
    values: dict | None = None,
) -> np.ndarray:
    """The model output at known values of the fitted parameters (``ks``, ``kd`` and/or
    ``values``: name -> value, every one of ``cal.problem.names``) plus seeded Gaussian noise
    (sd ``noise``, output units)."""
    known = dict(values or {}, **{n: v for n, v in (("ks", ks), ("kd", kd)) if v is not None})
    missing = [n for n in cal.problem.names if n not in known]
    if missing:
        raise ValueError(f"synthetic_target needs a value of every fitted parameter; missing {missing}")
    why = beyond_history(cal.problem.gains, cal.problem.options.h, {n: known[n] for n in cal.problem.names})
    if why is not None:
        raise ValueError(f"synthetic_target: {why}")
    x = np.log([known[n] for n in cal.problem.names])
    ev = (evaluator or ResponseEvaluator(cal.problem, cal.jacobian))(x)
    if np.any(ev.diverged >= 0):
        raise FitError(f"the rollout diverges at {describe(cal.problem.names, x)}; cannot make a synthetic target")
    rng = np.random.default_rng(seed)
    return ev.y + noise * rng.standard_normal(ev.y.shape)


def write_synthetic_target(
    config_path,
    ks: float | None = None,
    kd: float | None = None,
    values: dict | None = None,
    noise_deg: float = 0.0,
    seed: int = 0,
    progress: bool = True,
) -> pathlib.Path:
    """Simulate a joint-angle target at known values of the config's fitted parameters (``[fit]
    parameters``, default ks and kd: ``ks``, ``kd`` and/or ``values``) and write it to the
    config's target file.

    The config's ``[fit.target]`` must be ``kind = "joint_angles"`` with ``file`` and ``dofs``;
    the CSV covers the fit window on the simulation grid, in the config's ``angle_unit``, with
    seeded Gaussian noise of ``noise_deg`` degrees added.
    """
    from neuromotor.config.fields import Fields, read_toml
    from neuromotor.config.parse import fit_spec, simulation_config
    from neuromotor.studies.simulate import prepare
    from neuromotor.studies.targets import write_target_csv

    config_path = pathlib.Path(config_path)
    data = read_toml(config_path)
    cfg = simulation_config(data, str(config_path), config_path.parent)
    raw = data.get("fit", {}).get("target", {}) if isinstance(data.get("fit"), dict) else {}
    t = Fields(raw, "fit.target", cfg.source)
    if t.get("kind") != "joint_angles":
        t.fail("kind", "must be 'joint_angles' to write a synthetic trajectory target")
    if not isinstance(t.get("file"), str) or not t.get("dofs"):
        t.fail("file" if not isinstance(t.get("file"), str) else "dofs", "is required to write a synthetic target")
    spec = fit_spec(data, cfg, config_path.parent)
    setup = prepare(cfg)
    model, dofs = setup.model, list(spec.target.names)
    for i, n in enumerate(dofs):
        if n not in model.dof_names:
            raise ConfigError(f"{cfg.source}: field 'fit.target.dofs[{i}]' is an unknown DOF name {n!r}")
    problem = make_problem(
        setup, "joint_angles", [model.dof_names.index(n) for n in dofs], spec.window, names=spec.parameters
    )
    known = dict(values or {}, **{n: v for n, v in (("ks", ks), ("kd", kd)) if v is not None})
    missing = [n for n in problem.names if n not in known]
    if missing:
        raise ConfigError(
            f"{cfg.source}: the synthetic target needs a value of every fitted parameter "
            f"(fit.parameters); missing {missing}"
        )
    why = beyond_history(problem.gains, problem.options.h, {n: known[n] for n in problem.names})
    if why is not None:
        raise ConfigError(f"{cfg.source}: the synthetic target's {why}")
    cal = Calibration(setup=setup, problem=problem, target=np.zeros(1), weights=np.zeros(1), x0=np.zeros(2))
    y = synthetic_target(
        cal,
        noise=np.deg2rad(noise_deg),
        seed=seed,
        evaluator=ResponseEvaluator(problem),
        values={n: known[n] for n in problem.names},
    )
    vals = y.reshape(problem.n_cases, -1, len(dofs))
    unit = spec.target.angle_unit
    if unit == "deg":
        vals = np.rad2deg(vals)
    at = ", ".join(f"{n} = {known[n]:g} {UNITS[n]}" for n in problem.names)
    note = (
        f"synthetic target: neuromotor rollout at {at}, h = {setup.options.h}\n"
        f"plus Gaussian noise of sd {noise_deg} deg (seed {seed}); angles in {unit}; config {config_path.name}"
    )
    return write_target_csv(spec.target.file, cal.time, dofs, vals, "joint_angles", note)


def truth_recovery(
    cal: Calibration,
    truth: dict,
    noise: float,
    seeds,
    evaluator: ResponseEvaluator | None = None,
    progress: bool = True,
) -> list[dict]:
    """The synthetic-truth check: for each seed, the model output at the known values ``truth``
    (name -> value, every fitted parameter) plus Gaussian noise of sd ``noise`` (output units),
    fitted back from ``cal.x0``. One row per seed (seed None: no noise) with the fitted values,
    their standard errors, the errors against the truth and the identifiability verdict."""
    from neuromotor.studies.fit.driver import fit

    ev = evaluator or ResponseEvaluator(cal.problem, cal.jacobian)
    rows = []
    for seed in seeds:
        target = synthetic_target(cal, noise=0.0 if seed is None else noise, seed=seed or 0, evaluator=ev, values=truth)
        res = fit(ev, target, cal.weights, cal.x0, cal.solver, cal.options, progress=progress)
        row = {
            "seed": seed,
            "noise": 0.0 if seed is None else noise,
            "status": res.status,
            "iterations": res.iterations,
            "identifiable": all(res.identifiable.values()),
        }
        for n in cal.problem.names:
            row.update(
                {
                    n: res.values[n],
                    f"se_{n}": res.standard_errors[n],
                    f"error_{n}": res.values[n] - truth[n],
                    f"z_{n}": (res.values[n] - truth[n]) / res.standard_errors[n]
                    if res.standard_errors[n] > 0
                    else float("nan"),
                }
            )
        rows.append(row)
    return rows


def record_trial(
    data: dict, ks: float, kd: float, out_dir, source: str = "<recorded trial>", character=None, traj=None
) -> pathlib.Path:
    """A 'recorded trial' with a known truth: the config table ``data`` (``[sim]``, the clip,
    ``[[perturbation]]``) simulated at (ks, kd), written as ``out_dir/run.npz`` and exported by
    ``export-bvh`` as ``out_dir/trial.bvh`` in the clip's own skeleton (channels of joints the
    model does not simulate follow the capture). Frame 0 is at clip time ``sim.start``. Returns
    the BVH's path."""
    from neuromotor.config.parse import simulation_config
    from neuromotor.io.export import export_bvh
    from neuromotor.studies.record import run_arrays
    from neuromotor.studies.simulate import config_character, prepare, run, save_npz_atomic

    cfg = simulation_config(data, source).with_gains(ks, kd)
    if character is None:
        character, traj = config_character(cfg)
    setup = prepare(cfg, character, traj)
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    save_npz_atomic(out_dir / "run.npz", run_arrays(setup, run(setup)))
    return export_bvh(out_dir / "run.npz", out_dir / "trial.bvh")
