"""The shipped walk on a free root on the ground (issue 38, docs/balance.md "Walking").

    .venv/bin/python experiments/walk_free.py [--seconds 6]

Two feedforwards, no perturbation, no assist, clip time 0.5 s on: (a) what ``[sim] root =
"free"`` gives (the capture's inverse dynamics with the driven root, the first pose's standing
support folded in, the postural loop on); (b) the contact-aware inverse
(:func:`neuromotor.studies.residuals.ground_reference`: the capture's ground reaction forces as
known external forces), the loop off. Prints the fall (time into the run, first body) and the COM
sway.
"""

from __future__ import annotations

import argparse
import dataclasses

import _common  # float64, compile cache; the repository root

from neuromotor.config import simulation_config
from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.studies.balance import falls, sway
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.residuals import ground_reference
from neuromotor.studies.simulate import prepare

CLIP = str(_common.REPO.parent / "shared" / "mocap" / "walk_22joint_zyx.bvh")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0)
    args = ap.parse_args()
    sim = {"root": "free", "start": 0.5, "duration": args.seconds}
    for label, contact_ff in (("(a) root = free as configured", False), ("(b) contact-aware feedforward", True)):
        data = {"clip": CLIP, "sim": sim}
        if contact_ff:
            data["balance"] = {"enabled": False}
        setup = prepare(simulation_config(data, "<walk>"))
        if contact_ff:
            driven = dataclasses.replace(setup.options, free_root=False)
            ref, _ = ground_reference(setup.character, setup.traj, setup.ref, driven)
            setup = dataclasses.replace(setup, ref=ref)
        out = simulate_contact_jit(setup.sim_model, setup.params, ground_scene(setup.ground))
        f, sw = falls(setup, out), sway(setup, out)
        print(
            f"{label}: fell {f['fell']} at {f['fall_time_s']} s ({f['fall_body']}), "
            f"sway RMS {sw['sway_rms_mm']:.0f} mm, diverged step {int(out.run.diverged_step)}"
        )


if __name__ == "__main__":
    main()
