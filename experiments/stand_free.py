"""Measurement (issue 38): how long does the character stand on its own feet?

    .venv/bin/python experiments/stand_free.py [--frame N] [--seconds 4] [--h 0.008333]

One frame of the embedded clip (default: the stillest of its first 2 s, a standing pose) held
for ``--seconds`` (a still clip written to a temporary directory), simulated with
``[sim] root = "free"``: the pelvis has no actuator and no constraint, the ground (on by
default with a free root, at the still clip's floor: its lowest foot point) carries the body
through the feet's polyhedra, and the joints get the feedforward of the standing frame (the
capture's inverse dynamics with the driven root, the paper's) plus the feedback at the default
gains. No balance controller: the feedforward was computed with the pelvis held, so it does not
know that the legs now carry the trunk.

Prints the pelvis height above the floor over time, when it has dropped by 5 and 20 cm,
when a body other than a foot first touches the ground, and the ground's normal force.
"""

from __future__ import annotations

import argparse
import pathlib
import tempfile
import time

import _common  # noqa: F401  (float64, compile cache)
import jax.numpy as jnp
import numpy as np

from neuromotor.config import simulation_config
from neuromotor.model.bvh import read_bvh, write_bvh
from neuromotor.model.load import default_clip_path
from neuromotor.physics.contact import lowest_points, simulate_contact_jit
from neuromotor.rotations import quat_to_matrix
from neuromotor.studies.ground import foot_bodies, ground_scene
from neuromotor.studies.simulate import prepare


def stillest_frame(clip, seconds: float = 2.0) -> int:
    """The frame of the first ``seconds`` whose channels change least (central difference)."""
    n = max(3, min(clip.n_frames, int(seconds / clip.frame_time)))
    motion = clip.motion[:n]
    change = np.abs(motion[2:] - motion[:-2]).sum(-1)
    return int(np.argmin(change)) + 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frame", type=int, default=None)
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--h", type=float, default=1.0 / 120.0)
    ap.add_argument("--per-body", type=int, default=None, help="[ground] contacts_per_body (default 8)")
    ap.add_argument("--max-contacts", type=int, default=None, help="[ground] max_contacts (default 16)")
    args = ap.parse_args()
    clip = read_bvh(default_clip_path())
    frame = stillest_frame(clip) if args.frame is None else args.frame
    n = int(round(args.seconds / clip.frame_time)) + 2
    with tempfile.TemporaryDirectory() as tmp:
        path = pathlib.Path(tmp) / "still.bvh"
        write_bvh(path, clip, np.repeat(clip.motion[frame : frame + 1], n, 0))
        data = {"clip": str(path), "up_axis": 1, "sim": {"root": "free", "duration": args.seconds, "h": args.h}}
        ground = {"contacts_per_body": args.per_body, "max_contacts": args.max_contacts}
        data["ground"] = {k: v for k, v in ground.items() if v is not None}
        data["balance"] = {"enabled": False}  # the bare free root (the postural loop: stand_balance.py)
        setup = prepare(simulation_config(data, "<stand_free>"))
        t0 = time.perf_counter()
        out = simulate_contact_jit(setup.sim_model, setup.params, ground_scene(setup.ground))
        wall = time.perf_counter() - t0
    model, ground = setup.model, setup.ground
    assert ground is not None
    up = -np.asarray(model.gravity) / np.linalg.norm(np.asarray(model.gravity))
    time_s = np.asarray(out.run.time) - float(out.run.time[0])
    pelvis = np.asarray(out.run.states.pos[:, 0]) @ up - float(ground.height)
    lam = np.asarray(out.contact.normal_impulse)
    bodies = np.asarray(ground.slot_body)
    feet = foot_bodies(setup.character)
    other = lam[:, ~np.isin(bodies, feet)].sum(-1) > 0
    name = default_clip_path().name
    print(f"frame {frame} of {name} (t = {frame * clip.frame_time:.3f} s), h = {args.h:.6g} s,")
    print(f"{ground.per_body} contacts per body, {ground.max_contacts} in all")
    print(
        f"floor {float(ground.height):.4f} m, mass {float(np.sum(model.mass)):.1f} kg, {wall:.1f} s wall (with compile)"
    )
    if int(out.run.diverged_step) >= 0:
        print(f"diverged at step {int(out.run.diverged_step)} (t = {time_s[int(out.run.diverged_step) + 1]:.3f} s)")
    for t in np.arange(0.0, args.seconds + 1e-9, 0.25):
        k = int(round(t / args.h))
        force = lam[k].sum() / args.h if k > 0 else 0.0
        print(f"  t {t:5.2f} s  pelvis {pelvis[k]:.3f} m  ground force {force:7.1f} N")
    for drop in (0.05, 0.20):
        below = np.nonzero(pelvis < pelvis[0] - drop)[0]
        when = f"{time_s[below[0]]:.3f} s" if below.size else "never"
        print(f"pelvis {100 * drop:.0f} cm below its start: {when}")
    first = np.nonzero(other)[0]
    who = ""
    if first.size:
        k = first[0]
        who = ", ".join(sorted({model.body_names[b] for b in bodies[(lam[k] > 0) & ~np.isin(bodies, feet)]}))
    when = f"{time_s[first[0]]:.3f} s ({who})" if first.size else "never"
    print(f"first ground contact of a body other than a foot: {when}")
    states = out.run.states
    deepest = np.asarray(lowest_points(model, ground, states.pos, quat_to_matrix(states.quat)))
    print(
        f"deepest penetration of any polyhedron vertex: {max(0.0, -deepest.min()) * 1000:.2f} mm "
        f"(at t = {time_s[int(np.argmin(deepest))]:.3f} s)"
    )
    weight = float(np.sum(model.mass)) * float(jnp.linalg.norm(model.gravity))
    mean = lam[1 : int(0.5 / args.h) + 1].sum(-1).mean() / args.h
    print(f"mean ground force over the first 0.5 s: {mean:.1f} N (weight {weight:.1f} N)")


if __name__ == "__main__":
    main()
