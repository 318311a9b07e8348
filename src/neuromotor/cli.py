"""The ``neuromotor`` command line.

    neuromotor inspect [CLIP.bvh] [--json]
    neuromotor idyn [CLIP.bvh] -o OUT.npz
    neuromotor simulate [CONFIG.toml] -o RUN.npz [--ks KS --kd KD] [--json]
    neuromotor render RUN.npz -o OUT.png|OUT.mp4|OUT.gif
    neuromotor export-bvh RUN.npz -o OUT.bvh
    neuromotor demo [-o DIR]        # the main job: simulate the default hit, render it

Every command writes its outputs atomically and exits non-zero with a one-line message on bad
input, leaving no partial file behind.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np


def _table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(str(r[i])) for r in rows + [header]) for i in range(len(header))]
    line = lambda r: "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()
    return "\n".join([line(header), line(["-" * w for w in widths])] + [line(r) for r in rows])


def model_json(character) -> dict:
    """The ``inspect --json`` contract."""
    model, clip = character.model, character.clip
    joints = []
    cols = {}
    for i, name in enumerate(model.dof_names):
        cols.setdefault(name.split(".")[0], []).append(name)
    for k, joint in enumerate(clip.joints):
        b = model.joint_body[k]
        body = None
        if b >= 0:
            body = {
                "mass": float(model.mass[b]),
                "com": [float(x) for x in model.com[b]],
                "inertia": [[float(x) for x in row] for row in model.inertia[b]],
            }
        joints.append({
            "name": joint.name,
            "parent": clip.joints[joint.parent].name if joint.parent >= 0 else None,
            "offset": [float(x) for x in model.joint_offset[k]],
            "channels": list(joint.channels),
            "dofs": cols.get(joint.name, []) if joint.parent >= 0 else [],
            "body": body,
        })
    return {
        "source": str(clip.path),
        "gravity": [float(x) for x in model.gravity],
        "frame_time": clip.frame_time,
        "frames": clip.n_frames,
        "total_mass": float(np.sum(model.mass)),
        "joints": joints,
    }


def cmd_inspect(args) -> int:
    from .simulate import load_character

    character, _ = load_character(args.clip, args.units, args.up_axis)
    if args.json:
        print(json.dumps(model_json(character), indent=2))
        return 0
    model, clip = character.model, character.clip
    rows = []
    for k, joint in enumerate(clip.joints):
        b = model.joint_body[k]
        n_dof = sum(1 for d in model.dof_body if b >= 0 and d == b)
        rows.append([joint.name, clip.joints[joint.parent].name if joint.parent >= 0 else "-",
                     f"{float(model.mass[b]):.3f}" if b >= 0 else "(none)",
                     "root (6, driven)" if joint.parent < 0 else str(n_dof),
                     " ".join(joint.channels)])
    print(f"clip      {clip.path}")
    print(f"frames    {clip.n_frames} at {1.0 / clip.frame_time:.2f} Hz, {clip.duration:.3f} s")
    print(f"units     {clip.length_scale:g} m per file unit")
    print(f"bodies    {model.n_bodies}, simulated DOFs {model.n_dofs}, constraint rows {model.n_constraints}")
    print(f"mass      {float(np.sum(model.mass)):.2f} kg total\n")
    print(_table(rows, ["joint", "parent", "mass kg", "DOFs", "channels"]))
    return 0


def cmd_idyn(args) -> int:
    from .inverse import idyn_arrays
    from .simulate import load_character, save_npz_atomic

    character, traj = load_character(args.clip, args.units, args.up_axis)
    clip = character.clip
    times = np.arange(clip.n_frames) * clip.frame_time
    arrays = idyn_arrays(character.model, traj, times)
    arrays["joint_names"] = np.array(character.model.joint_names)
    save_npz_atomic(args.output, arrays)
    print(f"wrote {args.output}: {len(times)} frames, {len(arrays['dof_names'])} DOFs, "
          f"max Eq. 3 residual {arrays['kkt_residual'].max():.2e}")
    return 0


def _sim_config(args):
    from .config import SimulationConfig, DEFAULT_HIT, load_simulation_config

    if args.config:
        cfg = load_simulation_config(args.config)
    else:
        cfg = SimulationConfig(perturbations=[dict(DEFAULT_HIT)], duration=3.0, source="<default>")
    if args.ks is not None:
        cfg.ks = args.ks
    if args.kd is not None:
        cfg.kd = args.kd
    return cfg


def cmd_simulate(args) -> int:
    from .simulate import prepare, run, run_arrays, save_npz_atomic

    setup = prepare(_sim_config(args))
    result = run(setup)
    save_npz_atomic(args.output, run_arrays(setup, result))
    if args.json:
        print(json.dumps(result.metrics, indent=2))
    else:
        m = result.metrics
        print(f"wrote {args.output}: peak deviation {m['peak_deviation_deg']:.2f} deg at "
              f"{m['time_of_peak_s']:.2f} s, recovery {m['recovery_time_s']:.2f} s, "
              f"unperturbed RMS error {m['unperturbed_rms_error_deg']:.2f} deg")
    return 0


def cmd_render(args) -> int:
    from .render import render_run

    render_run(args.run, args.output, frames=args.frames)
    print(f"wrote {args.output}")
    return 0


def cmd_export_bvh(args) -> int:
    from .export import export_bvh

    export_bvh(args.run, args.output)
    print(f"wrote {args.output}")
    return 0


def cmd_demo(args) -> int:
    out = pathlib.Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    ns = argparse.Namespace(config=None, ks=None, kd=None, json=False, output=out / "run.npz")
    cmd_simulate(ns)
    from .render import render_run

    for name in ("filmstrip.png", "video.mp4"):
        render_run(out / "run.npz", out / name)
        print(f"wrote {out / name}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="neuromotor", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)

    def clip_args(sp):
        sp.add_argument("clip", nargs="?", default=None, help="BVH file (default: embedded clip)")
        sp.add_argument("--units", default="auto", help="auto, m, cm, mm, in, or metres per unit")
        sp.add_argument("--up-axis", type=int, default=1, choices=(0, 1, 2))

    sp = sub.add_parser("inspect", help="bodies, masses, DOFs of a clip")
    clip_args(sp)
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_inspect)

    sp = sub.add_parser("idyn", help="inverse dynamics (Eq. 3) on every frame")
    clip_args(sp)
    sp.add_argument("-o", "--output", required=True)
    sp.set_defaults(func=cmd_idyn)

    sp = sub.add_parser("simulate", help="perturbed forward simulation (Eq. 2)")
    sp.add_argument("config", nargs="?", default=None)
    sp.add_argument("-o", "--output", required=True)
    sp.add_argument("--ks", type=float)
    sp.add_argument("--kd", type=float)
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_simulate)

    sp = sub.add_parser("render", help="filmstrip PNG or MP4/GIF of a run")
    sp.add_argument("run")
    sp.add_argument("-o", "--output", required=True)
    sp.add_argument("--frames", type=int, default=6)
    sp.set_defaults(func=cmd_render)

    sp = sub.add_parser("export-bvh", help="write the perturbed motion as BVH")
    sp.add_argument("run")
    sp.add_argument("-o", "--output", required=True)
    sp.set_defaults(func=cmd_export_bvh)

    sp = sub.add_parser("demo", help="main job: simulate the default hit on the embedded clip and render it")
    sp.add_argument("-o", "--output", default="out/demo")
    sp.set_defaults(func=cmd_demo)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from .bvh import BvhError
    from .config import ConfigError
    from .dynamics import SimulationDiverged

    try:
        return args.func(args)
    except (BvhError, ConfigError, SimulationDiverged, FileNotFoundError, ValueError, KeyError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else e
        print(f"neuromotor {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
