"""The shipped walk on a free root on the ground (issue 38, docs/balance.md "Walking").

    .venv/bin/python experiments/walk_free.py [--seconds 6]

Two feedforwards, no perturbation, no assist, clip time 0.5 s on: (a) what ``[sim] root =
"free"`` gives (the capture's inverse dynamics with the driven root, the first pose's standing
support folded in, the postural loop on); (b) the contact-aware inverse
(:func:`neuromotor.studies.residuals.ground_reference`: the capture's ground reaction forces as
known external forces), the loop off; (c) that inverse with the loop on (the first pose's lean;
no standing support folded in, the capture's ground forces already carry the body). Prints the
fall (time into the run, first body), the COM sway and the step at which the rollout blew up
(-1: it did not).
"""

from __future__ import annotations

import argparse
import dataclasses

import _common  # float64, compile cache; the repository root
import jax.numpy as jnp

from neuromotor.config import simulation_config
from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.studies.balance import balance_for, falls, sway
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.residuals import ground_reference
from neuromotor.studies.simulate import prepare

CLIP = str(_common.REPO.parent / "shared" / "mocap" / "walk_22joint_zyx.bvh")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=6.0)
    args = ap.parse_args()
    sim = {"root": "free", "start": 0.5, "duration": args.seconds}
    cases = (
        ("(a) root = free as configured", False, False),
        ("(b) contact-aware feedforward, loop off", True, False),
        ("(c) contact-aware feedforward, loop on", True, True),
    )
    for label, contact_ff, loop in cases:
        data = {"clip": CLIP, "sim": sim}
        if contact_ff:
            data["balance"] = {"enabled": False}
        setup = prepare(simulation_config(data, "<walk>"))
        if contact_ff:
            driven = dataclasses.replace(setup.options, free_root=False)
            ref, _ = ground_reference(setup.character, setup.traj, setup.ref, driven)
            setup = dataclasses.replace(setup, ref=ref)
        if loop and contact_ff:
            bal = balance_for(setup.character, setup.ref.init, setup.options.h)
            bal = dataclasses.replace(bal, support=jnp.zeros_like(bal.support))
            setup = dataclasses.replace(setup, gains=dataclasses.replace(setup.gains, balance=bal))
        out = simulate_contact_jit(setup.sim_model, setup.params, ground_scene(setup.ground))
        f, sw = falls(setup, out), sway(setup, out)
        print(
            f"{label}: fell {f['fell']} at clip time {f['fall_time_s']} s ({f['fall_body']}), "
            f"sway RMS {sw['sway_rms_mm']:.0f} mm, diverged step {int(out.run.diverged_step)}"
        )


if __name__ == "__main__":
    main()
