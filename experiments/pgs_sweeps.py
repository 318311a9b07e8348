"""How far the ground's PGS sweeps are from converged (issue 38, docs/balance.md "Cost").

    .venv/bin/python experiments/pgs_sweeps.py [--seconds 2]

The embedded clip's most upright frame standing on a free root (postural loop on), pushed at the
pelvis 0.5 s in (0.1 s half-sine: 100 N forward, 150 N backward), simulated with 80, 40, 20, 10
and 5 PGS sweeps a step; prints the largest COM difference of each against 80 sweeps, beside the
push's peak COM excursion, and the contact solve's residual (``max_lcp_residual_mps``,
``lcp_residual_p95_mps``: docs/contact.md, step 5) at each sweep count.
"""

from __future__ import annotations

import argparse

import _common  # noqa: F401  (float64, compile cache)
import numpy as np

from neuromotor.config import simulation_config
from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.physics.contact.detection import ContactSettings
from neuromotor.studies.ground import ground_scene, lcp_figures
from neuromotor.studies.simulate import prepare
from neuromotor.studies.standing import standing_pose


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    args = ap.parse_args()
    path, character, traj, still = standing_pose()
    fwd = np.asarray(character.anatomy.forward, float)
    for sign, force in ((1.0, 100.0), (-1.0, 150.0)):
        push = {
            "kind": "force",
            "body": "pelvis",
            "direction": [float(x) for x in sign * fwd],
            "magnitude": force,
            "start": 0.5,
            "duration": 0.1,
            "shape": "half_sine",
        }
        data = {"clip": path, "sim": {"root": "free", "duration": args.seconds, "still": still}, "perturbation": [push]}
        setup = prepare(simulation_config(data, "<pgs>"), character, traj)
        mass = np.asarray(setup.model.mass)
        com, lcp = {}, {}
        for sweeps in (80, 40, 20, 10, 5):
            scene = ground_scene(setup.ground, ContactSettings(pgs_iterations=sweeps))
            out = simulate_contact_jit(setup.sim_model, setup.params, scene)
            com[sweeps] = np.einsum("b,tbi->ti", mass / mass.sum(), np.asarray(out.run.states.pos))
            lcp[sweeps] = lcp_figures(out.contact.step_residual, out.contact.touching)
        peak = 1e3 * np.abs(com[80] - com[80][0]).max()
        where = "forward" if sign > 0 else "backward"
        print(f"pelvis {where} {force:g} N: peak COM excursion {peak:.1f} mm (80 sweeps)")
        for sweeps in (80, 40, 20, 10, 5):
            r = lcp[sweeps]
            off = (
                ""
                if sweeps == 80
                else f"max |COM - COM(80 sweeps)| = {1e3 * np.abs(com[sweeps] - com[80]).max():.2f} mm, "
            )
            print(
                f"  {sweeps:2d} sweeps: {off}LCP residual max {r['max_lcp_residual_mps']:.2e} m/s, "
                f"p95 {r['lcp_residual_p95_mps']:.2e} m/s"
            )


if __name__ == "__main__":
    main()
