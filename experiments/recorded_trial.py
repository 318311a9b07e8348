"""The recorded-trial round trip on any clip (issue 35): simulate at known gains, export the run
as BVH (the clip's own skeleton: extremity channels follow the capture), fit (ks, kd) to that BVH
from a start off the truth, and print the recovered gains.

    python experiments/recorded_trial.py [CLIP.bvh ...] [--ks 300 --kd 15 --start-ks 800 --start-kd 40]
    python experiments/recorded_trial.py --rigs 7 11 --start 0.5

Without clips: every BVH in ../shared/mocap. ``--rigs``: the synthetic rigs of
tests/studies/test_recorded_trial.py instead (tests/synthetic_rigs.py: fingers, toes, face, random
names and Euler orders), their trials re-encoded in other Euler orders. Prints one line per clip
(docs/fitting.md).
"""

import argparse
import pathlib
import sys
import tempfile
import time

import _common  # noqa: F401  (float64, compile cache)

from neuromotor.studies.fit import calibrate, calibration_from_dict, record_trial
from neuromotor.studies.simulate import load_character

SHARED = _common.REPO.parent / "shared" / "mocap"


def round_trip_config(clip, start=1.0, duration=0.6, h=1 / 60, ks=800.0, kd=40.0, trial=None,
                      time_offset=None, hit_at=None, magnitude=300.0, max_steps=40) -> dict:
    """A fit config on ``clip``: a half-sine push on the chest, fit (ks, kd) over the whole window
    to the BVH ``trial`` (frame 0 at ``time_offset``, default the window's start)."""
    hit_at = start + 0.1 if hit_at is None else hit_at
    data = {
        "clip": str(clip),
        "sim": {"h": h, "start": start, "duration": duration},
        "gains": {"ks": ks, "kd": kd},
        "perturbation": [{"body": "chest", "point": [0.0, 0.1, 0.0], "direction": [0.0, 0.0, 1.0],
                          "magnitude": magnitude, "start": hit_at, "duration": 0.1, "shape": "half_sine"}],
        "fit": {"solver": "optimistix_lm", "window": [start, start + duration], "max_steps": max_steps},
    }
    if trial is not None:
        data["fit"]["target"] = {"kind": "joint_angles", "file": str(trial),
                                 "time_offset": start if time_offset is None else time_offset}
    return data


# The rigs of tests/studies/test_recorded_trial.py.
RIGS = {7: dict(fingers=True, toes=True, face=True, up="Y", unit="cm", virtual_root=False),
        11: dict(fingers=True, toes=True, face=True, six_channels=True, up="Z", unit="in", virtual_root=True)}


def synthetic_rig(seed: int, out_dir) -> tuple[pathlib.Path, list[str]]:
    """The rig of ``seed`` written to ``out_dir/rig.bvh``, and the other Euler orders its trial is
    re-encoded in (per CHANNELS line: XZY, or YXZ where the rig has XZY)."""
    sys.path.insert(0, str(_common.REPO / "tests"))
    from synthetic_rigs import make_rig

    from neuromotor.model.bvh import read_bvh

    path = pathlib.Path(out_dir) / "rig.bvh"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(make_rig(seed, frames=60, **RIGS[seed]).text)
    orders = ["YXZ" if j.rotation_order == "XZY" else "XZY" for j in read_bvh(path).joints if j.channels]
    return path, orders


def round_trip(clip, ks=300.0, kd=15.0, start_ks=800.0, start_kd=40.0, out_dir=None, orders=None, **kw):
    """(fit result, fit.json document, trial path) of the round trip on ``clip``; ``orders``: the
    trial re-encoded in these Euler orders (tests/synthetic_rigs.reencode)."""
    out_dir = pathlib.Path(out_dir or tempfile.mkdtemp(prefix="recorded_trial_"))
    character, traj = load_character(str(clip))
    trial = record_trial(round_trip_config(clip, **kw), ks, kd, out_dir, character=character, traj=traj)
    if orders is not None:
        from synthetic_rigs import reencode

        trial.write_text(reencode(trial.read_text(), orders))
    data = round_trip_config(clip, ks=start_ks, kd=start_kd, trial=trial, **kw)
    cal = calibration_from_dict(data, "<round trip>", character=character, traj=traj)
    return (*calibrate(cal, progress=False), trial)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("clips", nargs="*")
    ap.add_argument("--ks", type=float, default=300.0)
    ap.add_argument("--kd", type=float, default=15.0)
    ap.add_argument("--start-ks", type=float, default=800.0)
    ap.add_argument("--start-kd", type=float, default=40.0)
    ap.add_argument("--h", type=float, default=1 / 60)
    ap.add_argument("--start", type=float, default=1.0)
    ap.add_argument("--duration", type=float, default=0.6)
    ap.add_argument("--rigs", type=int, nargs="+", choices=sorted(RIGS), help="synthetic rigs instead of clips")
    args = ap.parse_args(argv)
    if args.rigs:
        cases = []
        for seed in args.rigs:
            path, orders = synthetic_rig(seed, tempfile.mkdtemp(prefix=f"rig{seed}_"))
            cases.append((f"rig {seed}", path, orders))
    else:
        cases = [(pathlib.Path(c).name, c, None) for c in args.clips or sorted(str(p) for p in SHARED.glob("*.bvh"))]
    for label, clip, orders in cases:
        t0 = time.perf_counter()
        res, doc, _ = round_trip(clip, args.ks, args.kd, args.start_ks, args.start_kd, orders=orders, h=args.h,
                                 start=args.start, duration=args.duration)
        v = res.values
        notes = "".join(f"{doc[k]}; " for k in ("not_fitted", "euler_orders_converted") if k in doc)
        print(f"{label}: ks = {v['ks']:.6g} ({v['ks'] / args.ks - 1:+.2e}), kd = {v['kd']:.6g} "
              f"({v['kd'] / args.kd - 1:+.2e}), {res.status}, {res.iterations} iterations, residual "
              f"{res.residual_norm:.3g} rad, {notes}{time.perf_counter() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
