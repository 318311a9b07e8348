"""Pushes on the standing posture (issue 38): the clip's most upright frame on a free root on
the ground with the postural loop, a half-sine force on the pelvis or the chest from 8
horizontal directions, 0.5 s into a 3 s run.

    .venv/bin/python experiments/push_balance.py [--magnitudes 100 200] [--seconds 3]

Prints, per body, direction (degrees from the facing direction, counter-clockwise seen from
above) and magnitude: the impulse (N s), recovered or fell (time, body), the peak COM excursion
(mm) and the recovery time (s after the push's onset until the COM's horizontal speed stays
below 2 cm/s). "not settled": no fall detected, but still moving at the end or carried more than
30 cm (sliding or stumbling on the feet); "diverged": the rollout blew up.
"""

from __future__ import annotations

import argparse

import _common  # noqa: F401  (float64, compile cache)
import numpy as np

from neuromotor.config import simulation_config
from neuromotor.model.load import default_clip_path, load_character
from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.studies.balance import falls
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.simulate import prepare

ONSET, DURATION = 0.5, 0.1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--magnitudes", type=float, nargs="+", default=[100.0, 200.0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--bodies", nargs="+", default=["pelvis", "chest"])
    args = ap.parse_args()
    path = str(default_clip_path())
    probe = simulation_config({"clip": path}, "<push>")
    character, traj = load_character(probe.clip, probe.units, probe.up_axis, probe.stature, probe.mass_options())
    anatomy = character.anatomy
    assert anatomy is not None
    still = anatomy.reference_frame * character.clip.frame_time
    up, fwd = np.asarray(anatomy.up, float), np.asarray(anatomy.forward, float)
    side = np.cross(up, fwd)
    print(f"still frame t = {still:.3f} s; push {DURATION:g} s half-sine at {ONSET:g} s")
    print("body     dir  F(N)  J(Ns)  outcome            peak(mm)  recovery(s)")
    for body in args.bodies:
        for mag in args.magnitudes:
            for deg in range(0, 360, 45):
                a = np.radians(deg)
                d = np.cos(a) * fwd + np.sin(a) * side
                pert = {
                    "kind": "force",
                    "body": body,
                    "direction": [float(x) for x in d],
                    "magnitude": mag,
                    "start": ONSET,
                    "duration": DURATION,
                    "shape": "half_sine",
                }
                sim = {"root": "free", "duration": args.seconds, "still": still}
                cfg = simulation_config({"clip": path, "sim": sim, "perturbation": [pert]}, "<push>")
                setup = prepare(cfg, character, traj)
                out = simulate_contact_jit(setup.sim_model, setup.params, ground_scene(setup.ground))
                f = falls(setup, out)
                mass = np.asarray(setup.model.mass)
                com = np.einsum("b,tbi->ti", mass / mass.sum(), np.asarray(out.run.states.pos))
                hvel = np.diff(com, axis=0) / setup.options.h
                hvel -= np.outer(hvel @ up, up)
                speed = np.linalg.norm(hvel, axis=-1)
                k0 = int(round(ONSET / setup.options.h))
                disp = com - com[k0]
                disp -= np.outer(disp @ up, up)
                peak = 1000 * np.linalg.norm(disp[k0:], axis=-1).max()
                moving = np.nonzero(speed[k0:] >= 0.02)[0]
                rec = (moving[-1] + 1) * setup.options.h if moving.size else 0.0
                bad = int(out.run.diverged_step) >= 0
                if f["fell"]:
                    outcome = f"fell {f['fall_time_s'] - ONSET:.2f}s {f['fall_body']}"[:18]
                elif bad:
                    outcome = "diverged"
                elif rec > args.seconds - ONSET - 0.2 or peak > 300.0:
                    outcome = "not settled"  # still moving at the end, or carried off (sliding)
                else:
                    outcome = "recovered"
                recovery = f"{rec:.2f}" if outcome == "recovered" else "-"
                impulse = 2 / np.pi * mag * DURATION
                print(f"{body:7s} {deg:4d} {mag:5.0f} {impulse:5.1f}  {outcome:18s} {peak:8.1f}  {recovery}")


if __name__ == "__main__":
    main()
