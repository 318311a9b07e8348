"""How many kernels one free-standing step launches (issue 38's 20x real time).

    .venv/bin/python experiments/step_kernels.py [--sweeps 40]

Compiles the free-root rollout on the ground (the embedded clip's most upright frame, balance
on) and counts, in the optimized HLO, the instructions XLA:CPU runs as separate kernels (fusions,
dots, copies, custom calls, ...; not parameters, tuples, bitcasts or constants) in the time
loop's body and in each loop nested in it (the PGS sweep, the position projection, ...). A
nested loop runs its body once per iteration; the trip counts are the contact settings' (read
from the scene), so the step's kernel count is the body's plus each nested body's times its
count. At this model's sizes each kernel costs about 0.1 us of launch and bookkeeping beside
its arithmetic, so the count bounds the step's time from below. The count is a lower bound: small
helper loops (an LU's pivots, ...) are counted once and a called computation as one kernel.
"""

from __future__ import annotations

import argparse
import collections
import re

import _common  # noqa: F401  (float64, compile cache)

from neuromotor.physics.contact import simulate_contact_jit
from neuromotor.studies.ground import ground_scene
from neuromotor.studies.standing import standing_setup

FREE = {"parameter", "get-tuple-element", "tuple", "bitcast", "constant"}


def computations(text: str) -> dict[str, list[str]]:
    comps: dict[str, list[str]] = {}
    name = None
    for line in text.split("\n"):
        if line and not line.startswith(" ") and line.rstrip().endswith("{"):
            name = re.match(r"^(?:ENTRY )?%?([\w.\-]+)", line).group(1)
            comps[name] = []
        elif name and line.startswith("  "):
            comps[name].append(line)
    return comps


def kernels(lines: list[str]) -> collections.Counter:
    ops: collections.Counter = collections.Counter()
    for line in lines:
        m = re.search(r"= (?:\([^=]*\)|\S+) ([\w\-]+)\(", line)
        if m and m.group(1) not in FREE:
            ops[m.group(1)] += 1
    return ops


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.parse_args()
    s = standing_setup(0.5, 1.0 / 120.0, None)
    scene = ground_scene(s.ground)
    text = simulate_contact_jit.lower(s.sim_model, s.params, scene).compile().as_text()
    comps = computations(text)
    loops = []  # (parent, body)
    for parent, lines in comps.items():
        for line in lines:
            if " while(" in line:
                loops.append((parent, re.search(r"body=%?([\w.\-]+)", line).group(1)))
    # The time loop: the body with the most kernels whose loop sits in the entry computation.
    time_body = max((b for _, b in loops), key=lambda b: sum(kernels(comps[b]).values()))
    own = sum(kernels(comps[time_body]).values())
    print(f"time loop body: {own} kernels {dict(kernels(comps[time_body]).most_common(6))}")
    settings = scene.settings
    counts = {"pgs": settings.pgs_iterations, "position": settings.position_iterations}
    nested = sorted(
        ((sum(kernels(comps[b]).values()), b) for _, b in loops if b != time_body and b in comps),
        reverse=True,
    )
    total = own
    # The two largest nested bodies are the PGS sweep and the position projection (in that order:
    # the sweep updates three rows per contact, the projection one); the rest are small helpers
    # run once per step (counted once).
    for rank, (n, _body) in enumerate(nested):
        trips = counts["pgs"] if rank == 0 else counts["position"] if rank == 1 else 1
        total += n * trips
        if rank < 2:
            label = "PGS sweep" if rank == 0 else "position projection"
            print(f"{label}: {n} kernels per iteration x {trips} = {n * trips}")
    print(
        f"at least {total} kernels per step (the time loop's own, the sweeps, and {len(nested) - 2} small loops"
        " counted once, though some run more often, and called computations counted as one)"
    )


if __name__ == "__main__":
    main()
