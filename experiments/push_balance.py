"""Pushes on the standing posture (issue 38, docs/balance.md): the clip's most upright frame on
a free root on the ground with the postural loop (and stepping unless ``--no-stepping``), a
0.1 s half-sine force on the pelvis or the chest from 8 horizontal directions, 0.5 s into a
3 s run; all runs of a body batched into one vmapped rollout.

    .venv/bin/python experiments/push_balance.py [--impulses 5 10 15 20 30 40] [--seconds 3]
        [--bodies pelvis chest] [--no-stepping] [--figure docs/images/push_balance.png]

Directions: degrees from the facing direction, counter-clockwise seen from above (90: to the
left). Outcome of a run (the rule):

* fall: the fall detector (a non-foot body touches the ground, or the COM below 60 % of its
  height), or the rollout blew up, or the COM's horizontal distance from the nearer ankle
  exceeds 0.5 m at any time, or the COM still moves (>= 2 cm/s) in the last 0.2 s (not
  recovered: sliding or stumbling on);
* step: not a fall, and an ankle moved more than 5 cm horizontally from where it stood;
* sway: neither (recovered on the feet where they stood).

Recovery time: from the push's onset to the last instant the COM's horizontal speed is above
2 cm/s. Latency: from the onset to the first step where the postural loop's ankle torque
(recomputed from the recorded states with the run's gains and delay) differs from that of an
unpushed run (in the same batch) by more than 1 N m; and to the first lift-off of a stepping foot (ankle up by
more than 1 cm).
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import time

import _common  # noqa: F401  (float64, compile cache)
import jax
import jax.numpy as jnp
import numpy as np

from neuromotor.compiler import jit
from neuromotor.config import simulation_config
from neuromotor.physics.balance import joint_origins, posture_signals
from neuromotor.physics.contact import simulate_contact
from neuromotor.physics.dynamics import Params
from neuromotor.physics.reflex import delayed
from neuromotor.rotations import quat_to_matrix
from neuromotor.studies.balance import falls
from neuromotor.studies.ground import foot_bodies, ground_scene
from neuromotor.studies.simulate import prepare
from neuromotor.studies.standing import standing_pose

ONSET, DURATION = 0.5, 0.1
FAR = 0.5  # m: COM this far from the nearer ankle: a fall
STEP = 0.05  # m: an ankle moved this far: a step
SETTLED = 0.02  # m/s
TORQUE = 1.0  # N m: the postural loop's response threshold
LIFT = 0.01  # m


def setup_for(path, still, seconds, body, stepping, balance=None):
    pert = {
        "kind": "force",
        "body": body,
        "direction": [1.0, 0.0, 0.0],
        "magnitude": 1.0,
        "start": ONSET,
        "duration": DURATION,
        "shape": "half_sine",
    }
    sim = {"root": "free", "duration": seconds, "still": still}
    cfg = simulation_config(
        {"clip": path, "sim": sim, "perturbation": [pert], "balance": {"stepping": stepping} | (balance or {})},
        "<push>",
    )
    return prepare(cfg)


def postural_torque(setup, states):
    """The postural loop's ankle torque magnitude (N m) at each recorded step, from the states."""
    bal, model, h = setup.gains.balance, setup.model, setup.options.h
    angle, rate = jax.vmap(lambda s: posture_signals(model, bal, s))(states)
    n = angle.shape[0]
    pad = int(np.ceil(float(bal.delay) / h)) + 2

    def at(k):
        buf = lambda x: jax.lax.dynamic_slice_in_dim(jnp.concatenate([jnp.repeat(x[:1], pad, 0), x], 0), k, pad, 0)[
            ::-1
        ]
        a, r = delayed(buf(angle), bal.delay, h), delayed(buf(rate), bal.delay, h)
        return bal.mgh * jnp.linalg.norm(bal.kp * a[0] + bal.kd * r[0])

    return np.asarray(jax.vmap(at)(jnp.arange(1, n + 1)))


def classify(setup, out, i, up, base_torque):
    """One run's outcome, recovery time, peak excursion (mm) and latencies (module docstring)."""
    run = jax.tree_util.tree_map(lambda x: x[i], out)
    h = setup.options.h
    f = falls(setup, run)
    mass = np.asarray(setup.model.mass)
    states = run.run.states
    pos = np.asarray(states.pos)
    com = np.einsum("b,tbi->ti", mass / mass.sum(), pos)
    flat = lambda x: x - np.outer(x @ up, up) if x.ndim == 2 else x - (x @ up)[..., None] * up
    feet = list(foot_bodies(setup.character))
    rot = np.asarray(jax.vmap(quat_to_matrix)(states.quat))
    ankles = np.asarray(jax.vmap(lambda p, r: joint_origins(setup.model, p, r))(states.pos, rot))[:, feet]
    k0 = int(round(ONSET / h))
    gap = np.linalg.norm(flat(ankles - com[:, None]), axis=-1).min(-1)
    speed = np.linalg.norm(flat(np.diff(com, axis=0)) / h, axis=-1)
    moving = np.nonzero(speed[k0:] >= SETTLED)[0]
    rec = (moving[-1] + 1) * h if moving.size else 0.0
    moved = np.linalg.norm(flat(ankles - ankles[0]), axis=-1).max()
    bad = int(run.run.diverged_step) >= 0
    tail = speed[-int(round(0.2 / h)) :].max() >= SETTLED
    if f["fell"] or bad or gap.max() > FAR or tail:
        outcome = "fall"
    elif moved > STEP:
        outcome = "step"
    else:
        outcome = "sway"
    tq = postural_torque(setup, states)
    resp = np.nonzero(np.abs(tq[k0:] - base_torque[k0:]) > TORQUE)[0]
    rise = (ankles[:, :, None] - ankles[:1, :, None]) @ up[:, None]
    lifted = np.nonzero(rise[k0:, :, 0, 0].max(-1) > LIFT)[0]
    why = "detector" if f["fell"] else "diverged" if bad else f"far {gap.max():.2f}" if gap.max() > FAR else "moving"
    return {
        "outcome": outcome,
        "why": why if outcome == "fall" else "",
        "recovery": rec if outcome != "fall" else np.nan,
        "peak": 1000 * np.linalg.norm(flat(com[k0:] - com[k0]), axis=-1).max(),
        "latency": resp[0] * h if resp.size else np.nan,
        "liftoff": lifted[0] * h if lifted.size else np.nan,
    }


def figure(rows, impulses, dirs, bodies, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    codes = {"sway": 0, "step": 1, "fall": 2}
    fig, axes = plt.subplots(1, len(bodies) + 1, figsize=(4.2 * (len(bodies) + 1), 3.8))
    cmap = ListedColormap(["#4c9a2a", "#f0b429", "#c0392b"])
    for ax, body in zip(axes, bodies, strict=False):
        grid = np.array([[codes[rows[body, d, j]["outcome"]] for j in impulses] for d in dirs])
        ax.imshow(grid, cmap=cmap, vmin=0, vmax=2, aspect="auto", origin="lower")
        ax.set_xticks(range(len(impulses)), [f"{j:g}" for j in impulses])
        ax.set_yticks(range(len(dirs)), [f"{d}" for d in dirs])
        ax.set_xlabel("impulse (N s, 0.1 s half-sine)")
        ax.set_ylabel("direction (deg from facing, CCW)")
        ax.set_title(f"{body}: sway / step / fall")
    handles = [plt.Rectangle((0, 0), 1, 1, color=cmap(i)) for i in range(3)]
    axes[0].legend(handles, list(codes), loc="upper left", fontsize=7, framealpha=0.8)
    ax = axes[-1]
    for body, mark in zip(bodies, "os", strict=False):
        for d in dirs:
            rec = [rows[body, d, j]["recovery"] for j in impulses]
            ax.plot(impulses, rec, marker=mark, ms=3, lw=0.8, alpha=0.7, label=f"{body} {d}")
    ax.set_xlabel("impulse (N s)")
    ax.set_ylabel("recovery time (s after onset)")
    ax.set_title("recovery time (falls omitted)")
    ax.legend(fontsize=5, ncol=2)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    print(f"wrote {path}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--impulses", type=float, nargs="+", default=[5.0, 10.0, 15.0, 20.0, 30.0, 40.0])
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--bodies", nargs="+", default=["pelvis", "chest"])
    ap.add_argument("--directions", type=int, nargs="+", default=list(range(0, 360, 45)))
    ap.add_argument("--no-stepping", action="store_true")
    ap.add_argument("--figure", type=pathlib.Path, default=None)
    args = ap.parse_args()
    path, character, _, still = standing_pose()
    anatomy = character.anatomy
    assert anatomy is not None
    up, fwd = np.asarray(anatomy.up, float), np.asarray(anatomy.forward, float)
    side = np.cross(up, fwd)
    stepping = not args.no_stepping
    print(f"still frame t = {still:.3f} s; push {DURATION:g} s half-sine at {ONSET:g} s; stepping {stepping}")
    print("body     dir  J(Ns)  F(N)  outcome  peak(mm)  recovery(s)  latency(s)  liftoff(s)  why")
    run = lambda sim, gains, pulses, scene: simulate_contact(sim, Params(gains, pulses), scene)
    batched = jit(jax.vmap(run, in_axes=(None, None, 0, None)))
    rows = {}
    for body in args.bodies:
        setup = setup_for(path, still, args.seconds, body, stepping)
        cases = [(0, 0.0)] + [(d, j) for j in args.impulses for d in args.directions]  # first: no push
        pulses = []
        for d, j in cases:
            a = np.radians(d)
            direction = np.cos(a) * fwd + np.sin(a) * side
            mag = j * np.pi / (2 * DURATION)  # half-sine impulse = 2 F T / pi
            pulses.append(
                dataclasses.replace(
                    setup.pulses,
                    direction=jnp.asarray(direction, jnp.float64)[None],
                    magnitude=jnp.asarray([mag], jnp.float64),
                )
            )
        stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *pulses)
        t0 = time.perf_counter()
        out = batched(setup.sim_model, setup.params.gains, stacked, ground_scene(setup.ground))
        jax.block_until_ready(out)
        print(f"# {body}: {len(cases)} runs in {time.perf_counter() - t0:.0f} s (one vmapped call, with compilation)")
        base = postural_torque(setup, jax.tree_util.tree_map(lambda x: x[0], out.run.states))
        for i, (d, j) in enumerate(cases[1:], 1):
            rows[body, d, j] = classify(setup, out, i, up, base)
        for j in args.impulses:
            for d in args.directions:
                r = rows[body, d, j]
                mag = j * np.pi / (2 * DURATION)
                rec = "-" if np.isnan(r["recovery"]) else f"{r['recovery']:.2f}"
                lift = "-" if np.isnan(r["liftoff"]) else f"{r['liftoff']:.3f}"
                print(
                    f"{body:7s} {d:4d} {j:5.1f} {mag:5.0f}  {r['outcome']:7s} {r['peak']:8.1f}  {rec:>11s}"
                    f"  {r['latency']:10.3f}  {lift:>10s}  {r['why']}"
                )
    if args.figure is not None:
        figure(rows, args.impulses, args.directions, args.bodies, args.figure)


if __name__ == "__main__":
    main()
