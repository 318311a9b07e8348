"""Where a step's time goes: XLA:CPU kernels of the compiled rollout, grouped by the source function
that produced them (from a ``jax.profiler`` trace and the stack frames XLA keeps in the
optimized HLO).

    .venv/bin/python experiments/profile_step.py [--batch 256] [--solver branch] [--top 30] [--lines]

Prints, per function, the profiled microseconds per trajectory-step, the kernels per step and the
shape of one of its kernels. The profiler adds about a microsecond to every kernel, so read the
column as a ranking, and the kernel count as the cost of a single trajectory (bound by the
number of kernels) and the microseconds as the cost of a batch (bound by the work in them).
"""

import argparse
import collections
import dataclasses
import glob
import gzip
import json
import re
import tempfile

import _common  # noqa: F401


def _tables(txt: str) -> dict[str, dict[int, str]]:
    """The FileNames, FunctionNames, FileLocations and StackFrames tables at the end of the HLO text."""
    out = {}
    for name in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
        rows, part = {}, txt.split("\n" + name + "\n", 1)
        for line in (part[1].splitlines() if len(part) == 2 else []):
            if not line.strip():
                break
            key, value = line.split(" ", 1)
            rows[int(key)] = value.strip('"')
        out[name] = rows
    return out


def _sources(txt: str, lines: bool) -> dict[str, tuple[str, str]]:
    """Instruction name -> (innermost project frame outside rotations.py, its shape)."""
    t = _tables(txt)
    num = lambda field, v: int(re.search(rf"\b{field}=(\d+)", v).group(1))
    locs = {k: (t["FileNames"][num("file_name_id", v)].split("/")[-1], t["FunctionNames"][num("function_name_id", v)],
                num("line", v)) for k, v in t["FileLocations"].items()}
    frames = {k: (num("file_location_id", v), num("parent_frame_id", v)) for k, v in t["StackFrames"].items()}

    def where(fid: int) -> str:
        seen, chain = set(), []
        while fid in frames and fid not in seen:
            seen.add(fid)
            loc, fid = frames[fid]
            chain.append(locs[loc])
        for file, func, line in chain:
            if file != "rotations.py":
                return f"{file}:{func}" + (f":{line}" if lines else "")
        return ":".join(map(str, chain[0])) if chain else "?"

    out = {}
    for line in txt.splitlines():
        m = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = (\S+) ", line)
        frame = re.search(r"stack_frame_id=(\d+)", line)
        if m:
            out[m.group(1)] = (where(int(frame.group(1))) if frame else "?", m.group(2))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--batch", type=int, default=1, help="trajectories under vmap (1: one trajectory)")
    ap.add_argument("--solver", default=None, help="default: nullspace for one trajectory, branch for a batch")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--lines", action="store_true", help="group by source line, not by function")
    ap.add_argument("--free", action="store_true", help="the free root standing on the ground (issue 38), 2 s")
    ap.add_argument("--pgs", type=int, default=None, help="with --free: [ground] pgs_iterations")
    args = ap.parse_args(argv)
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_traceback_in_locations_limit", 200)
    from neuromotor import compiler
    from neuromotor.physics import dynamics as dy
    from neuromotor.studies import bench

    size, solver = args.batch, args.solver or ("nullspace" if args.batch == 1 else "branch")
    if args.free:
        from neuromotor.physics.contact import simulate_contact
        from neuromotor.studies.ground import ground_scene
        from neuromotor.studies.standing import standing_setup

        s = standing_setup(2.0, ground={"pgs_iterations": args.pgs} if args.pgs else None)
        args_, cfg = (s.sim_model, s.params, ground_scene(s.ground)), s.sim_model.options
        compiled = compiler.jit(simulate_contact).lower(*args_).compile()
    else:
        setup = bench._setup(None, 1.0 if size == 1 else 0.25, solver)
        m, g, p, ref, cfg = setup.model, setup.gains, setup.pulses, setup.ref, setup.options
        mags = jnp.linspace(0.5, 1.5, size)[:, None] * p.magnitude[None]

        def many(mags, g, ref):
            one = lambda mag: dy.rollout(m, g, dataclasses.replace(p, magnitude=mag), ref, cfg).theta
            return jax.vmap(one)(mags) if size > 1 else one(mags[0])

        args_ = (mags, g, ref)
        compiled = compiler.jit(many).lower(*args_).compile()
    source = _sources(compiled.as_text(), args.lines)
    jax.block_until_ready(compiled(*args_))
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            jax.block_until_ready(compiled(*args_))
        trace = glob.glob(f"{tmp}/**/*.trace.json.gz", recursive=True)[0]
        events = [e for e in json.load(gzip.open(trace))["traceEvents"] if e.get("ph") == "X"]
    time_of, count, shape = collections.Counter(), collections.Counter(), {}
    for e in events:
        if e["name"] in source:
            where, shp = source[e["name"]]
            time_of[where] += e["dur"]
            count[where] += 1
            shape.setdefault(where, shp)
    per = cfg.n_steps * size
    print(f"{solver}, batch {size}, {cfg.n_steps} steps: {sum(count.values()) / cfg.n_steps:.0f} kernels per step, "
          f"{sum(time_of.values()) / per:.1f} profiled us per trajectory-step")
    print("| us / traj-step | kernels / step | source | one kernel's shape |\n| --- | --- | --- | --- |")
    for where, t in time_of.most_common(args.top):
        print(f"| {t / per:.2f} | {count[where] / cfg.n_steps:.1f} | {where} | {shape[where][:40]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
