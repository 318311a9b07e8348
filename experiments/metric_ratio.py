"""The two deviation metrics on one run: the geodesic joint deviation (default) against the
per-DOF Euler form, from the body quaternions and angles a RUN.npz holds (README, "Joint errors").

    .venv/bin/neuromotor simulate -o out/run.npz
    .venv/bin/python experiments/metric_ratio.py out/run.npz
"""

import argparse

import numpy as np

import _common  # noqa: F401

from neuromotor.io.runfile import read_run
from neuromotor.studies import metrics as mx
from neuromotor.studies.simulate import load_character


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", help="RUN.npz written by neuromotor simulate")
    ap.add_argument("--above", type=float, default=0.05, help="samples with a geodesic d above this (deg)")
    args = ap.parse_args(argv)
    d = read_run(args.run, ("time", "dof_names", "theta", "theta_unperturbed", "theta_desired", "body_quat",
                            "body_quat_unperturbed", "source_clip"))
    model = load_character(str(d["source_clip"]))[0].model  # the skeleton's tree: which body is whose parent
    t = d["time"]
    geo = np.asarray(mx.joint_deviation(model, d["body_quat_unperturbed"], d["body_quat"]))
    eul = np.asarray(mx.deviation(d["theta"], d["theta_unperturbed"]))
    turn = np.asarray(mx.joint_angle_changes_deg(model, d["body_quat_unperturbed"], d["body_quat"]))
    print(f"geodesic peak {geo.max():.4f} deg at {t[geo.argmax()]:.4f} s; Euler peak {eul.max():.4f} deg at "
          f"{t[eul.argmax()]:.4f} s; largest single joint turn {turn.max():.4f} deg")
    moving = geo > args.above
    r = eul[moving] / geo[moving]
    print(f"Euler / geodesic over the {moving.sum()} samples with d > {args.above:g} deg: median {np.median(r):.4f}, "
          f"range {r.min():.4f} to {r.max():.4f}; at the geodesic peak {eul[geo.argmax()] / geo.max():.4f}; "
          f"1/sqrt(3) = {1 / np.sqrt(3):.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
