"""What the feet do in a stepping run (issue 38, docs/balance.md "Stepping, measured"): the
embedded clip's standing pose on a free root with stepping on, a 0.1 s half-sine pelvis push
0.5 s in; prints every 0.05 s the COM's travel and drop and, per foot, its ground normal force,
how many of its contact slots are active, its tilt (the angle of its sole's normal from the
vertical; the sole: the plane of the foot polyhedron's lowest vertices in the standing pose)
and its ankle's horizontal and vertical travel.

    .venv/bin/python experiments/step_trace.py [--impulse 15] [--direction 180] [--seconds 2.5]
        [--set swing_time=0.2 ...] [--search N --seed S]

``--set``: stepping parameters ([balance] keys of the Stepping container: margin, offset,
max_step, swing_time, lift, weight_shift, shift_fraction, crouch, blend). ``--search N``: N
random sets of those parameters (uniform in the ranges below; row 0 the defaults) in one
vmapped rollout instead, each classified by experiments/push_balance.py's outcome rule.
"""

from __future__ import annotations

import argparse
import dataclasses

import _common  # noqa: F401  (float64, compile cache)
import jax
import jax.numpy as jnp
import numpy as np
from push_balance import DURATION, ONSET, classify, postural_torque, setup_for

from neuromotor.compiler import jit
from neuromotor.physics.balance import joint_origins
from neuromotor.physics.contact import simulate_contact
from neuromotor.physics.contact.step import scene_candidate_bodies
from neuromotor.physics.dynamics import Params
from neuromotor.rotations import quat_to_matrix
from neuromotor.studies.ground import foot_bodies, ground_scene
from neuromotor.studies.standing import standing_pose

RANGES = {  # --search: uniform ranges of the stepping parameters
    "margin": (0.0, 0.08),
    "offset": (0.0, 0.25),
    "swing_time": (0.12, 0.35),
    "weight_shift": (0.01, 0.2),
    "shift_fraction": (0.0, 1.2),
    "crouch": (0.0, 0.06),
    "lift": (0.02, 0.08),
    "blend": (0.1, 0.6),
}


def with_stepping(gains, values: dict):
    bal = gains.balance
    sp = dataclasses.replace(bal.stepping, **{k: jnp.asarray(v, jnp.float64) for k, v in values.items()})
    return dataclasses.replace(gains, balance=dataclasses.replace(bal, stepping=sp))


def sole_normal(setup, foot: int, rot0, up) -> np.ndarray:
    """The foot's sole normal in its frame: the normal of the plane through its polyhedron's
    lowest vertices (the mass model builds a foot's sole flat), pointing up in the pose rot0."""
    shape = setup.character.shapes[foot]
    verts = np.asarray(getattr(shape, "vertices", shape)).reshape(-1, 3)
    low = verts[np.argsort((verts @ rot0.T) @ up)[: max(3, len(verts) // 2)]]
    normal = np.linalg.svd(low - low.mean(0))[2][-1]
    return normal if (rot0 @ normal) @ up > 0 else -normal


def trace(setup, out) -> None:
    model, h = setup.model, setup.options.h
    anatomy = setup.character.anatomy
    up, fwd = np.asarray(anatomy.up, float), np.asarray(anatomy.forward, float)
    states = out.run.states
    rot = jax.vmap(quat_to_matrix)(states.quat)
    ankle = np.asarray(jax.vmap(lambda p, r: joint_origins(model, p, r))(states.pos, rot))
    rot = np.asarray(rot)
    mass = np.asarray(model.mass)
    com = np.einsum("b,tbi->ti", mass / mass.sum(), np.asarray(states.pos))
    body = np.asarray(scene_candidate_bodies(ground_scene(setup.ground)))
    normal, active = np.asarray(out.contact.normal_impulse) / h, np.asarray(out.contact.active)
    feet = foot_bodies(setup.character)
    normals = {f: sole_normal(setup, f, rot[0, f], up) for f in feet}
    print("t(s)  COM back/fwd(mm) drop(mm) | per foot: N(N) slots tilt(deg) ankle fwd(mm) up(mm)")
    for k in range(0, normal.shape[0], int(round(0.05 / h))):
        row = f"{k * h:4.2f}  {(com[k] - com[0]) @ fwd * 1e3:8.1f} {(com[k] - com[0]) @ up * 1e3:8.1f}"
        for f in feet:
            tilt = np.degrees(np.arccos(np.clip((rot[k, f] @ normals[f]) @ up, -1.0, 1.0)))
            move = ankle[k, f] - ankle[0, f]
            on = body == f
            row += f" | {normal[k, on].sum():5.0f} {active[k, on].sum():2d} {tilt:5.1f}"
            row += f" {move @ fwd * 1e3:6.0f} {move @ up * 1e3:5.0f}"
        print(row)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--impulse", type=float, default=15.0)
    ap.add_argument("--direction", type=float, default=180.0, help="degrees from facing, CCW seen from above")
    ap.add_argument("--seconds", type=float, default=2.5)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--search", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    path, character, _, still = standing_pose()
    anatomy = character.anatomy
    assert anatomy is not None
    up, fwd = np.asarray(anatomy.up, float), np.asarray(anatomy.forward, float)
    a = np.radians(args.direction)
    direction = np.cos(a) * fwd + np.sin(a) * np.cross(up, fwd)
    setup = setup_for(path, still, args.seconds, "pelvis", True)
    pulses = dataclasses.replace(
        setup.pulses,
        direction=jnp.asarray(direction, jnp.float64)[None],
        magnitude=jnp.asarray([args.impulse * np.pi / (2 * DURATION)], jnp.float64),
    )
    gains = with_stepping(setup.params.gains, {k: float(v) for k, v in (s.split("=", 1) for s in args.set)})
    scene = ground_scene(setup.ground)
    print(
        f"pelvis push {args.impulse:g} N s toward {args.direction:g} deg at {ONSET:g} s;",
        f"stepping {args.set or 'defaults'}",
    )
    if not args.search:
        trace(setup, jit(simulate_contact)(setup.sim_model, Params(gains, pulses), scene))
        return
    rng = np.random.default_rng(args.seed)
    sp = gains.balance.stepping
    values = {
        k: np.concatenate([[float(getattr(sp, k))], rng.uniform(lo, hi, args.search - 1)])
        for k, (lo, hi) in RANGES.items()
    }
    run = lambda v: simulate_contact(setup.sim_model, Params(with_stepping(gains, v), pulses), scene)
    out = jit(jax.vmap(run))({k: jnp.asarray(v) for k, v in values.items()})
    still_run = simulate_contact(
        setup.sim_model, Params(gains, dataclasses.replace(pulses, magnitude=0.0 * pulses.magnitude)), scene
    )
    base = postural_torque(setup, still_run.run.states)
    counts: dict[str, int] = {}
    for i in range(args.search):
        r = classify(setup, out, i, up, base)
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
        shown = " ".join(f"{k}={values[k][i]:.3f}" for k in RANGES)
        print(f"{i:3d} {r['outcome']:5s} {r['why']:10s} {shown}")
    print("outcomes:", counts)


if __name__ == "__main__":
    main()
