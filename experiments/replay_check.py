"""Unperturbed replay and a chest push on every shipped clip, per feedforward and joint law (the
figures of docs/discrete.md). Joint errors are geodesic: the angle of R_a^T R_b of each joint's
local rotation, which no Euler convention distorts.

    .venv/bin/python experiments/replay_check.py [CLIP.bvh ...] [--h 0.00833 0.01667]
        [--duration 3 | --whole] [--modes discrete/rotation continuous/euler]
"""

import argparse
import pathlib
import time

import numpy as np

import _common  # noqa: F401

from neuromotor.config import SimulationConfig
from neuromotor.rotations import quat_conj, quat_log, quat_mul
from neuromotor.studies.simulate import prepare, run

SHARED = _common.REPO.parent / "shared" / "mocap"
PUSH = dict(kind="force", body="chest", point=None, direction=[1.0, 0.0, 0.0], magnitude=300.0,
            start=1.0, duration=0.1, shape="half_sine")


def geodesic_deg(model, quat, rel_quat) -> np.ndarray:
    """(T, C): each joint's angle (deg) between its local rotation and ``rel_quat``'s."""
    topo = model.topology
    rel = quat_mul(quat_conj(quat[:, topo.parent]), quat[:, topo.child])
    return np.degrees(np.linalg.norm(np.asarray(quat_log(quat_mul(quat_conj(rel_quat), rel))), axis=-1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("clips", nargs="*", default=sorted(str(p) for p in SHARED.glob("*.bvh")))
    ap.add_argument("--h", type=float, nargs="+", default=[1.0 / 120.0], help="time steps (s)")
    ap.add_argument("--duration", type=float, default=3.0, help="simulated seconds from the clip's start")
    ap.add_argument("--whole", action="store_true", help="the whole clip (no push)")
    ap.add_argument("--modes", nargs="+", default=["discrete/rotation", "continuous/euler"],
                    help="feedforward/joint_law pairs")
    args = ap.parse_args(argv)
    print("| clip | h s | steps | feedforward / law | replay max deg (joint) | replay RMS deg | push peak deg | "
          "at +1.8 s / peak | prepare + run s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for path in args.clips:
        for h in args.h:
            for mode in args.modes:
                ff, law = mode.split("/")
                kw = dict(clip=path, h=h, feedforward=ff, joint_law=law)
                if args.whole:
                    cfg = SimulationConfig(**kw)
                else:
                    cfg = SimulationConfig(duration=args.duration, perturbations=[dict(PUSH)], **kw)
                t0 = time.perf_counter()
                setup = prepare(cfg)
                res = run(setup)
                seconds = time.perf_counter() - t0
                model = setup.model
                base, pert = res.unperturbed, res.perturbed
                err = geodesic_deg(model, base.states.quat, setup.ref.rel_quat[: base.time.shape[0]])
                worst = np.unravel_index(int(np.argmax(err)), err.shape)
                push = "-"
                if not args.whole:
                    topo = model.topology
                    rel = quat_mul(quat_conj(base.states.quat[:, topo.parent]), base.states.quat[:, topo.child])
                    dev = np.sqrt(np.mean(geodesic_deg(model, pert.states.quat, rel) ** 2, axis=-1))
                    t = np.asarray(pert.time)
                    later = dev[np.argmin(np.abs(t - (PUSH["start"] + 1.8)))]
                    push = f"{dev.max():.3f} | {later / dev.max():.3f}"
                else:
                    push = "- | -"
                print(f"| {pathlib.Path(path).stem} | {h:.5f} | {setup.options.n_steps} | {ff} / {law} | "
                      f"{err.max():.2e} ({model.body_names[worst[1] + 1]}) | {np.sqrt(np.mean(err**2)):.2e} | "
                      f"{push} | {seconds:.0f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
