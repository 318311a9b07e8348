"""Every shipped clip end to end at the default gains: body model, unperturbed replay and a
300 N push on the chest (the figures of docs/body-model.md).

    .venv/bin/python experiments/every_clip.py [CLIP.bvh ...] [--h SECONDS] [--duration 3]
"""

import argparse
import pathlib

import numpy as np

import _common  # noqa: F401

from neuromotor.config import SimulationConfig
from neuromotor.studies import metrics as mx
from neuromotor.studies.simulate import prepare, run

SHARED = _common.REPO.parent / "shared" / "mocap"
PUSH = dict(kind="force", body="chest", point=None, direction=[1.0, 0.0, 0.0], magnitude=300.0,
            start=1.0, duration=0.1, shape="half_sine")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("clips", nargs="*", default=sorted(str(p) for p in SHARED.glob("*.bvh")))
    ap.add_argument("--h", type=float, default=1.0 / 120.0, help="time step (s)")
    ap.add_argument("--duration", type=float, default=3.0, help="simulated seconds from the clip's start")
    args = ap.parse_args(argv)
    print("| clip | units | stature m | mass kg | bodies | replay RMS deg | worst joint RMS deg | "
          "push peak deg | at s | recovery s | final deg |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in args.clips:
        setup = prepare(SimulationConfig(clip=path, h=args.h, duration=args.duration, perturbations=[dict(PUSH)]))
        res = run(setup)
        # geodesic joint errors of the replay against the mocap's local rotations (README, "Joint errors")
        local = mx.joint_quats(setup.model, res.unperturbed.states.quat)
        err = np.degrees(np.asarray(mx.geodesic_angle(local, setup.ref.rel_quat[: local.shape[0]])))
        per_joint = np.sqrt(np.mean(err**2, axis=0))
        worst = int(np.argmax(per_joint))
        anat, model, m = setup.character.anatomy, setup.model, res.metrics
        print(f"| {pathlib.Path(path).stem} | {anat.units} | {anat.stature:.2f} | {float(np.sum(model.mass)):.1f} | "
              f"{model.n_bodies} | {m['unperturbed_rms_error_deg']:.2f} | {per_joint[worst]:.2f} "
              f"({model.body_names[int(model.topology.child[worst])]}) | {m['peak_deviation_deg']:.2f} | "
              f"{m['time_of_peak_s']:.2f} | {m['recovery_time_s']:.2f} | {m['final_error_deg']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
