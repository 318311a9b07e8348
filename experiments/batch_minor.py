"""The tree factorization and solve with the batch as the minor (last) axis, against ``vmap``.

    .venv/bin/python experiments/batch_minor.py [--batch 256] [--repeats 200]

Issue 17 suggested making the batch the innermost axis of the hot stages, so that every 3x3
block operation runs as a contiguous loop over the trajectories. This measures the idea on the
tree solver (:mod:`neuromotor.physics.solvers.branch`, the embedded clip's tree, random SPD
moments) without a second copy of it: ``factor`` and ``solve`` run unchanged on arrays laid out
``(bodies, ..., 3, 3, batch)``, with their 3x3 helpers swapped for versions that index the
matrix axes in front of the batch axis. Both layouts give the same numbers to the last bit
(checked). Timed alternately, medians of the rounds' ratios:

* ``factor`` alone, and ``solve`` alone, each with its inputs already in its layout;
* the moves between the layouts that a batch-minor solver inside a batch-first step would pay:
  the paths (row and column blocks of every tree level) and a right-hand side (B, 3) in and out.
"""

import argparse
import time

import _common  # noqa: F401


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=200)
    args = ap.parse_args(argv)
    import jax
    import jax.numpy as jnp
    import numpy as np

    from neuromotor import compiler
    from neuromotor.physics.solvers import branch
    from neuromotor.studies import bench

    # 3-vectors on axis -2 and 3x3 matrices on axes (-3, -2), the batch last
    def cross(a, b):
        return jnp.stack([a[..., 1, :] * b[..., 2, :] - a[..., 2, :] * b[..., 1, :],
                          a[..., 2, :] * b[..., 0, :] - a[..., 0, :] * b[..., 2, :],
                          a[..., 0, :] * b[..., 1, :] - a[..., 1, :] * b[..., 0, :]], -2)

    def inv3(a):
        c0, c1, c2 = a[..., :, 0, :], a[..., :, 1, :], a[..., :, 2, :]
        r0, r1, r2 = cross(c1, c2), cross(c2, c0), cross(c0, c1)
        det = c0[..., 0, :] * r0[..., 0, :] + c0[..., 1, :] * r0[..., 1, :] + c0[..., 2, :] * r0[..., 2, :]
        return jnp.stack([r0, r1, r2], -3) / det[..., None, None, :]

    def mm(a, b):
        return sum(a[..., :, k, None, :] * b[..., None, k, :, :] for k in range(3))

    def mv(a, x):
        return sum(a[..., :, k, :] * x[..., k, None, :] for k in range(3))

    model = bench._setup(None, 0.25, "branch").model
    sch = branch.schedule(model.topology, True)
    n, b = args.batch, model.n_bodies
    k1, k2, k3, k4 = jax.random.split(jax.random.PRNGKey(0), 4)
    a = 0.1 * jax.random.normal(k1, (n, b, 3, 3)) + 3.0 * jnp.eye(3)
    c_blocks = jnp.einsum("nbij,nbkj->nbik", a, a)
    first, pivot = 0.1 * jax.random.normal(k2, (n, b, 3)), 0.1 * jax.random.normal(k3, (n, b, 3))
    rhs = jax.random.normal(k4, (n, b, 3))
    paths = jax.vmap(lambda c, f, p: branch.paths_of(sch, c, f, p))(c_blocks, first, pivot)
    to_minor = lambda tree: jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 0, -1), tree)
    build = lambda f, *x: compiler.jit(f).lower(*x).compile()

    fac_first = build(jax.vmap(lambda p: branch.factor(sch, p)), paths)
    fac = fac_first(paths)
    solve_first = build(jax.vmap(lambda f, r: branch.solve(sch, f, r)), fac, rhs)
    minor_paths, minor_fac, minor_rhs = to_minor(paths), to_minor(fac), to_minor(rhs)
    saved = branch.mm, branch.mv, branch.inv3
    branch.mm, branch.mv, branch.inv3 = mm, mv, inv3
    try:
        fac_minor = build(lambda p: branch.factor(sch, p), minor_paths)
        solve_minor = build(lambda f, r: branch.solve(sch, f, r), minor_fac, minor_rhs)
    finally:
        branch.mm, branch.mv, branch.inv3 = saved
    move_paths = build(to_minor, paths)
    move_rhs = build(lambda r: jnp.moveaxis(jnp.moveaxis(r, 0, -1) * 2.0, -1, 0), rhs)

    leaves = lambda t: [x for x in jax.tree_util.tree_leaves(t) if x.size]
    diff = max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(leaves(to_minor(fac)), leaves(fac_minor(minor_paths))))
    diff = max(diff, float(jnp.max(jnp.abs(to_minor(solve_first(fac, rhs)) - solve_minor(minor_fac, minor_rhs)))))
    print(f"largest difference between the layouts' factors and solutions: {diff:.1e}")

    calls = {"factor, batch first": (fac_first, (paths,)), "factor, batch minor": (fac_minor, (minor_paths,)),
             "solve, batch first": (solve_first, (fac, rhs)),
             "solve, batch minor": (solve_minor, (minor_fac, minor_rhs)),
             "paths to batch minor": (move_paths, (paths,)), "a right-hand side there and back": (move_rhs, (rhs,))}
    times = {name: [] for name in calls}
    for _ in range(args.repeats):
        for name, (fn, x) in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(fn(*x))
            times[name].append(time.perf_counter() - t)
    t = {name: np.array(v) for name, v in times.items()}
    for name in calls:
        print(f"{name:>34}: {t[name].min() / n * 1e6:6.2f} us per trajectory (best)")
    for stage in ("factor", "solve"):
        ratio = np.median(t[f"{stage}, batch first"] / t[f"{stage}, batch minor"])
        print(f"{stage}: batch minor {ratio:.2f}x as fast as batch first (median of the rounds' ratios)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
