"""Issue 37's synthetic truth: gains fitted to sled-test corridors, and how honest their errors are.

A still upright posture from a shipped clip (the frame where the character stands most upright),
trunk and pelvis belted (``[sim] driven_joints = ["trunk", "pelvis"]``), each subject its own
recorded T1 acceleration (a 15 g, 100 ms half-sine deceleration, backward, varied per subject and
sampled at 1 kHz as a CSV in g and ms), h = 1 ms. Simulated at known gains and reflex delay, the
head's pitch (about the character's left axis, against the world) and the head's displacement
relative to the chest (along forward) are written as CSV corridors with Gaussian noise of the
corridor's sd; the fit starts 3x off and must come back within 2 % (the delay within 2 ms).
Repeated over noise seeds, the fraction of fits whose 95 % interval holds the truth says whether
the reported standard errors are honest; the leave-one-out errors are the fit's own report.

    python experiments/sled_fit.py [--out out/sled_fit] [--seeds 20] [--first-seed 0] [--subjects 4] [--clip CLIP.bvh]
    python experiments/sled_fit.py --write-example configs/targets/sled   # the shipped worked example

``--write-example`` writes the inputs and the corridors of one seed beside
``configs/fit_sled.toml`` (README and docs/fitting.md: ``neuromotor fit configs/fit_sled.toml``).
"""

import argparse
import json
import pathlib
import sys
import time

import _common  # noqa: F401  (float64, compile cache)
import numpy as np

TRUTH = {"ks": 1500.0, "kd": 60.0, "reflex_delay": 0.03}  # 1/s^2, 1/s, s
START = {"ks": 4500.0, "kd": 20.0, "reflex_delay": 0.09}  # 3x off each way
REFLEX_GAIN = 600.0  # 1/s^2, held (fitting it too is a config line: [fit] parameters)
SD = {"pitch": 2.0, "disp": 3.0}  # corridor sd: deg, mm
ONSET = 0.02  # s into the window: each record's time 0
WINDOW = 0.3  # s simulated
H = 0.001


def subject_input(i: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Subject i's T1 acceleration (ms, g): a half-sine deceleration of 15 g +- 10 % and
    100 ms +- 10 % over the subjects, sampled at 1 kHz, with 20 ms of quiet before and after."""
    u = 0.0 if n == 1 else (i / (n - 1) - 0.5)
    peak, dur = 15.0 * (1.0 + 0.2 * u), 100.0 * (1.0 - 0.2 * u)
    t = np.arange(-20.0, dur + 20.0 + 0.5, 1.0)
    a = np.where((t >= 0) & (t <= dur), peak * np.sin(np.pi * np.clip(t / dur, 0.0, 1.0)), 0.0)
    return t, a


def config(folder: pathlib.Path, n: int, clip: str | None, still: float, start=START, loo: bool = True) -> dict:
    """The fit config (as TOML would give it) reading the subjects' files in ``folder``."""
    cases = [f"s{i}" for i in range(n)]
    data = {
        "sim": {"still": still, "start": 0.0, "duration": WINDOW, "h": H, "driven_joints": ["trunk", "pelvis"]},
        "gains": {"ks": start["ks"], "kd": start["kd"]},
        "reflex": {"gain": REFLEX_GAIN, "delay": start["reflex_delay"]},
        "perturbation": [
            {"kind": "base", "direction": "backward", "file": str(folder / f"{c}_t1_acceleration.csv"), "unit": "g",
             "time_unit": "ms", "start": ONSET}
            for c in cases
        ],
        "fit": {
            "solver": "optimistix_lm", "max_steps": 60, "parameters": ["ks", "kd", "reflex_delay"],
            "leave_one_out": loo,
            "target": [
                {"kind": "body_angle", "body": "head", "relative_to": "world", "axis": "left",
                 "files": [str(folder / f"{c}_head_pitch.csv") for c in cases], "time_unit": "ms", "angle_unit": "deg"},
                {"kind": "body_position", "body": "head", "relative_to": "chest", "axis": "forward",
                 "files": [str(folder / f"{c}_head_t1.csv") for c in cases], "time_unit": "ms", "length_unit": "mm"},
            ],
        },
    }
    if clip is not None:
        data["clip"] = clip
    return data


def write_inputs(folder: pathlib.Path, n: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        t, a = subject_input(i, n)
        rows = "\n".join(f"{x:g},{y:.6f}" for x, y in zip(t, a))
        (folder / f"s{i}_t1_acceleration.csv").write_text(
            f"# subject {i}: T1 acceleration of a frontal sled deceleration (synthetic; g, ms from onset)\n"
            f"time,t1_x\n{rows}\n"
        )


def write_corridors(folder: pathlib.Path, n: int, truth_curves, seed: int | None) -> None:
    """Head pitch (deg) and head-minus-chest displacement (mm) per subject: the truth plus
    N(0, sd) noise (none with ``seed`` None), with the sd column."""
    rng = None if seed is None else np.random.default_rng(seed)
    times_ms, curves = truth_curves
    for i in range(n):
        for key, name, col in (("pitch", "head_pitch", "pitch"), ("disp", "head_t1", "head_x")):
            mean = curves[key][i] + (0.0 if rng is None else rng.normal(0.0, SD[key], times_ms.shape))
            rows = "\n".join(f"{t:g},{m:.6f},{SD[key]:g}" for t, m in zip(times_ms, mean))
            (folder / f"s{i}_{name}.csv").write_text(f"time,{col},{col}.sd\n{rows}\n")


def truth_curves(folder, n, clip, still, character):
    """The targets' curves at the truth: a calibration on placeholder corridors, evaluated there."""
    from neuromotor.studies.fit import calibration_from_dict
    from neuromotor.studies.fit.evaluate import ResponseEvaluator

    times_ms = np.arange(0.0, (WINDOW - ONSET) * 1000.0 - 0.5, 1.0)
    zeros = (times_ms, {"pitch": [np.zeros_like(times_ms)] * n, "disp": [np.zeros_like(times_ms)] * n})
    write_corridors(folder, n, zeros, None)
    cal = calibration_from_dict(config(folder, n, clip, still, TRUTH, loo=False), "truth", folder, character=character[0],
                                traj=character[1])
    ev = ResponseEvaluator(cal.problem, cal.jacobian)
    y = np.asarray(ev(cal.x0).y).reshape(n, cal.time.size, -1)
    (b0, b1) = cal.blocks
    pitch = np.degrees(y[:, :, b0["columns"][0]])
    disp = 1000.0 * y[:, :, b1["columns"][0]]
    grid_ms = (np.asarray(cal.time) - ONSET) * 1000.0
    keep = np.isin(np.round(times_ms, 6), np.round(grid_ms, 6))
    at = [int(np.argmin(abs(grid_ms - t))) for t in times_ms[keep]]
    return times_ms[keep], {"pitch": pitch[:, at], "disp": disp[:, at]}


def fit_once(folder, n, clip, still, character, out=None):
    """One fit from the start values; leave-one-out only for the one written to ``out``."""
    from neuromotor.studies.fit import calibrate, calibration_from_dict

    cal = calibration_from_dict(config(folder, n, clip, still, loo=out is not None), "sled", folder,
                                character=character[0], traj=character[1])
    res, doc = calibrate(cal, out, progress=False)
    return res, doc


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/sled_fit")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0, help="noise seeds first-seed .. first-seed + seeds - 1")
    ap.add_argument("--subjects", type=int, default=4)
    ap.add_argument("--clip", default=None, help="a BVH clip (default: the embedded one)")
    ap.add_argument("--write-example", default=None, help="write the inputs and seed 0's corridors to this folder")
    args = ap.parse_args(argv)

    from neuromotor.studies.simulate import load_character

    character = load_character(args.clip)
    an = character[0].anatomy
    still = round(an.reference_frame * character[0].clip.frame_time, 6)
    print(f"still pose at {still} s (frame {an.reference_frame}, the most upright), h = {H} s, {args.subjects} subjects")
    n = args.subjects
    folder = (pathlib.Path(args.write_example or args.out) / ("" if args.write_example else "data")).resolve()
    write_inputs(folder, n)
    t0 = time.perf_counter()
    truth = truth_curves(folder, n, args.clip, still, character)
    print(f"truth simulated in {time.perf_counter() - t0:.1f} s: head pitch peaks "
          f"{', '.join(f'{p.max():.1f}' for p in truth[1]['pitch'])} deg; head-chest "
          f"{', '.join(f'{d.max():.1f}' for d in truth[1]['disp'])} mm")
    if args.write_example:
        write_corridors(folder, n, truth, 0)
        print(f"wrote {folder}")
        return 0
    out = pathlib.Path(args.out)
    names = list(TRUTH)
    rows = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        write_corridors(folder, n, truth, seed)
        t1 = time.perf_counter()
        res, doc = fit_once(folder, n, args.clip, still, character, out / f"seed{seed}" if not rows else None)
        err = {k: res.values[k] / TRUTH[k] - 1.0 for k in names}
        z = {k: (res.values[k] - TRUTH[k]) / res.standard_errors[k] for k in names}
        rows.append({"seed": seed, "status": res.status, "iterations": res.iterations, "values": res.values,
                     "standard_errors": res.standard_errors, "relative_error": err, "z": z,
                     "leave_one_out": doc.get("leave_one_out"), "seconds": time.perf_counter() - t1})
        print(f"seed {seed:2d}: {res.status}, {res.iterations} it, "
              + ", ".join(f"{k} {res.values[k]:.5g} +- {res.standard_errors[k]:.2g} ({100 * err[k]:+.2f} %)"
                          for k in names) + f"  [{time.perf_counter() - t1:.0f} s]", flush=True)
    z = np.array([[r["z"][k] for k in names] for r in rows])
    rel = np.array([[r["relative_error"][k] for k in names] for r in rows])
    coverage = np.mean(np.abs(z) < 1.96, axis=0)
    summary = {
        "truth": TRUTH, "start": START, "reflex_gain": REFLEX_GAIN, "sd": SD, "h": H, "subjects": n, "still": still,
        "clip": args.clip or "embedded", "seeds": list(range(args.first_seed, args.first_seed + args.seeds)),
        "coverage_95": dict(zip(names, coverage.tolist())),
        "z_sd": dict(zip(names, z.std(axis=0, ddof=1).tolist())) if len(rows) > 1 else None,
        "max_abs_relative_error": dict(zip(names, np.max(np.abs(rel), axis=0).tolist())),
        "max_abs_delay_error_ms": float(np.max(np.abs(rel[:, 2])) * TRUTH["reflex_delay"] * 1000.0),
        "runs": rows,
    }
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    print("coverage of the 95 % intervals: " + ", ".join(f"{k} {c:.2f}" for k, c in zip(names, coverage)))
    print("largest error: " + ", ".join(f"{k} {100 * e:.2f} %" for k, e in zip(names, np.max(np.abs(rel), axis=0)))
          + f" (delay {summary['max_abs_delay_error_ms']:.2f} ms)")
    loo = rows[0]["leave_one_out"] or []
    for c in loo:
        pred = "; ".join(f"{p['target']}: {p['rms']:.3g} {p['unit']} ({p['rms_sd'] or float('nan'):.2f} sd)"
                         for p in c["predicted"])
        print(f"leave-one-out, subject {c['case']}: {pred}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
