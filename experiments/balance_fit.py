"""A synthetic truth for fitting the postural loop's gains (issue 38, docs/balance.md "Fitting the
loop"): ``configs/fit_balance.toml`` simulated at known ankle gains, its target (the pelvis's
displacement along forward after each push, mm) written with Gaussian noise.

    python experiments/balance_fit.py --write-example configs/targets [--noise-mm 0.5] [--seed 0]
    python experiments/balance_fit.py --seeds 10     # how honest the standard errors are

``--write-example`` writes ``balance_push.csv`` for the shipped config. ``--seeds N`` fits N noisy
copies (one per seed, the config's start) and prints the fraction of 95 % intervals that hold
the truth and the spread of the estimates against the reported standard errors.
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile

import _common  # float64, compile cache; the repository root
import numpy as np

from neuromotor.config.fields import read_toml
from neuromotor.studies import fit as F
from neuromotor.studies.fit.calibration import calibration_from_dict
from neuromotor.studies.fit.evaluate import ResponseEvaluator
from neuromotor.studies.fit.parameters import describe

CONFIG = _common.REPO / "configs" / "fit_balance.toml"
TRUTH = {"balance_kp": 1.5, "balance_kd": 0.45}  # m g H per rad, m g H s per rad
NAME = "balance_push.csv"


def _calibration(target: pathlib.Path, balance: dict | None = None):
    data = read_toml(CONFIG)
    data["fit"]["target"]["file"] = str(target)
    if balance is not None:
        data["balance"] = data.get("balance", {}) | balance
    return calibration_from_dict(data, str(CONFIG), CONFIG.parent)


def truth_rows() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(case, time from the case's onset (s), pelvis displacement (mm)) at the truth."""
    with tempfile.TemporaryDirectory() as tmp:
        # A placeholder covering the window, so that the problem has its shape; then the truth.
        probe = pathlib.Path(tmp) / NAME
        t = np.round(np.arange(-0.1, 1.2, 1.0 / 120.0), 9)
        probe.write_text("case,time,pelvis\n" + "".join(f"{c},{x:.9f},0.0\n" for c in range(2) for x in t))
        cal = _calibration(probe, {k.removeprefix("balance_"): v for k, v in TRUTH.items()})
    p = cal.problem
    _, curves, diverged = p.outputs(np.log([TRUTH[n] for n in p.names]))
    assert int(np.max(diverged)) < 0, "the truth's runs blew up"
    sim_time = np.asarray(p.ref.time)[p.spec.i0 : p.spec.i1]
    cases = np.repeat(np.arange(p.n_cases), sim_time.size)
    times = np.concatenate([sim_time - float(p.start[c]) for c in range(p.n_cases)])
    return cases, times, 1000.0 * np.asarray(curves)[:, :, 0].reshape(-1)


def write(path: pathlib.Path, rows, noise_mm: float, seed: int) -> None:
    cases, times, mm = rows
    noisy = mm + noise_mm * np.random.default_rng(seed).standard_normal(mm.shape)
    lines = "".join(f"{c},{t:.9f},{v:.6f}\n" for c, t, v in zip(cases, times, noisy))
    path.write_text(f"# pelvis displacement along forward (mm) at kp = {TRUTH['balance_kp']}, kd = "
                    f"{TRUTH['balance_kd']}, noise {noise_mm} mm (seed {seed}); experiments/balance_fit.py\n"
                    f"case,time,pelvis\n{lines}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write-example", default=None, help="write balance_push.csv to this folder")
    ap.add_argument("--noise-mm", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seeds", type=int, default=0, help="fit this many noisy copies")
    args = ap.parse_args(argv)
    rows = truth_rows()
    if args.write_example:
        folder = pathlib.Path(args.write_example)
        folder.mkdir(parents=True, exist_ok=True)
        write(folder / NAME, rows, args.noise_mm, args.seed)
        print(f"wrote {folder / NAME}")
    if args.seeds:
        x_true = np.log([TRUTH["balance_kp"], TRUTH["balance_kd"]])
        with tempfile.TemporaryDirectory() as tmp:
            path = pathlib.Path(tmp) / NAME
            write(path, rows, 0.0, 0)
            cal = _calibration(path)
        ev = ResponseEvaluator(cal.problem, cal.jacobian)
        est, se = [], []
        for seed in range(args.seeds):
            noise = 1e-3 * args.noise_mm * np.random.default_rng(seed).standard_normal(cal.target.shape)
            res = F.fit(ev, cal.target + noise, cal.weights, cal.x0, cal.solver, cal.options, progress=False)
            est.append(res.x)
            se.append(res.se_log)
            print(f"seed {seed}: {describe(cal.problem.names, res.x)} ({res.status}, {res.iterations} iterations)")
        est, se = np.array(est), np.array(se)
        inside = np.abs(est - x_true) <= 1.96 * se
        print(
            f"95 % intervals holding the truth (kp, kd): {inside.mean(0)}; RMS error of the log estimates "
            f"{np.sqrt(np.mean((est - x_true) ** 2, 0))} against the mean reported se {se.mean(0)}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
