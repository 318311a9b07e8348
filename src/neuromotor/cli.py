"""The ``neuromotor`` command line.

    neuromotor inspect [CLIP.bvh] [--json]
    neuromotor idyn [CLIP.bvh] -o OUT.npz [--opensim-dir DIR]   # DIR: model.osim, motion.mot, inverse_dynamics.sto
    neuromotor simulate [CONFIG.toml] -o RUN.npz [--ks KS --kd KD] [--json] [--opensim-dir DIR]
    neuromotor render RUN.npz -o OUT.png|OUT.mp4|OUT.gif
    neuromotor plot RUN.npz -o OUT.png    # deviation and joint angles vs time (matplotlib)
    neuromotor view RUN.npz -o OUT.html   # interactive 3-D viewer, one self-contained page (three.js)
    neuromotor export-bvh RUN.npz -o OUT.bvh
    neuromotor export-gltf RUN.npz -o OUT.glb|OUT.gltf [--layout ghost|shared]  # Blender, Unity, three.js
    neuromotor sweep CONFIG.toml [-o DIR] [--fitted KS KD | --fitted-json FIT.json]  # batch grid -> CSV + plots
        [--local-processes N | --coordinator HOST:PORT --num-processes N --process-id I | --distributed]
    neuromotor fit CONFIG.toml [-o DIR] [--solver NAME]   # calibrate (ks, kd) -> fit.json + fit.png
    neuromotor experiment CONFIG.toml [-o DIR]   # one of the paper's experiments ([experiment] kind)
    neuromotor demo [-o DIR]        # the main job: simulate the default hit, render it
    neuromotor bench [CLIP.bvh] [--plot PNG] [--json OUT]   # speed figures (docs/benchmarks.md)
    neuromotor export-mjcf [CLIP.bvh] -o MODEL.xml          # the same model for MuJoCo
    neuromotor export-osim [CLIP.bvh] -o MODEL.osim         # the same model for OpenSim (docs/opensim.md)
    neuromotor info RUN.npz [--json]   # provenance: version, clip SHA-256, resolved config, metrics

Every command writes its outputs atomically and exits non-zero with a one-line message on bad
input, leaving no partial file behind. Outputs are checked before any computation: one that is
an input of the command, an existing directory (for a file), under a regular file, or in a folder
that cannot be written is refused with exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import sys

import numpy as np


def _table(rows: list[list[str]], header: list[str]) -> str:
    widths = [max(len(str(r[i])) for r in rows + [header]) for i in range(len(header))]
    line = lambda r: "  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip()
    return "\n".join([line(header), line(["-" * w for w in widths])] + [line(r) for r in rows])


def metrics_json(metrics: dict) -> dict:
    """Metrics as strict JSON: NaN and infinities become null, and ``null_reasons`` says why."""
    why = {"recovery_time_s": "the deviation does not stay below recovery_threshold_deg before the window ends"}
    out: dict = {}
    reasons: dict[str, str] = {}
    for key, value in metrics.items():
        if isinstance(value, float) and not math.isfinite(value):
            out[key] = None
            reasons[key] = why.get(key, f"{value} (not a finite number)")
        else:
            out[key] = value
    if reasons:
        out["null_reasons"] = reasons
    return out


def model_json(character) -> dict:
    """The ``inspect --json`` contract."""
    model, clip, anat = character.model, character.clip, character.anatomy
    joints = []
    cols: dict[str, list[str]] = {}
    for name in model.dof_names:
        cols.setdefault(name.rsplit(".", 1)[0], []).append(name)
    for k, joint in enumerate(clip.joints):
        b = model.joint_body[k]
        body = None
        if b >= 0:
            body = {
                "mass": float(model.mass[b]),
                "com": [float(x) for x in model.com[b]],
                "inertia": [[float(x) for x in row] for row in model.inertia[b]],
            }
        joints.append(
            {
                "name": joint.name,
                "parent": clip.joints[joint.parent].name if joint.parent >= 0 else None,
                "offset": [float(x) for x in model.joint_offset[k]],
                "channels": list(joint.channels),
                "dofs": cols.get(joint.name, []) if joint.parent >= 0 else [],
                "segment": anat.segment[k],
                "side": anat.side[k] or None,
                "body": body,
            }
        )
    return {
        "source": str(clip.path),
        "units": anat.units,
        "length_scale": clip.length_scale,
        "stature": anat.stature,
        "up": [float(x) for x in anat.up],
        "shape_frame": anat.shape_frame,  # null: shapes built on the zero pose (the skeleton alone)
        "warnings": list(character.warnings),
        "gravity": [float(x) for x in model.gravity],
        "frame_time": clip.frame_time,
        "frames": clip.n_frames,
        "total_mass": float(np.sum(model.mass)),
        "joints": joints,
    }


def _load(args):
    """The character of a command's clip with its --units, --up-axis and body options."""
    from neuromotor.model.skeleton import MassModelOptions
    from neuromotor.studies.simulate import load_character

    options = MassModelOptions(body_mass=args.body_mass, sex=args.sex, simulate_extremities=args.simulate_extremities)
    return load_character(args.clip, args.units, args.up_axis, args.stature, options)


def _segment_label(character, k: int) -> str:
    anat = character.anatomy
    side = anat.side[k]
    return anat.segment[k] + (f" ({side[0].upper()})" if side else "")


def cmd_inspect(args) -> int:
    character, _ = _load(args)
    if args.json:
        print(json.dumps(model_json(character), indent=2))
        return 0
    model, clip, anat = character.model, character.clip, character.anatomy
    rows = []
    for k, joint in enumerate(clip.joints):
        b = model.joint_body[k]
        n_dof = sum(1 for d in model.dof_body if b >= 0 and d == b)
        rows.append(
            [
                joint.name,
                clip.joints[joint.parent].name if joint.parent >= 0 else "-",
                _segment_label(character, k),
                f"{float(model.mass[b]):.3f}" if b >= 0 else "(none)",
                "root (6, driven)" if joint.parent < 0 else str(n_dof),
                " ".join(joint.channels),
            ]
        )
    up = "+-"[int(anat.up.sum() < 0)] + "XYZ"[anat.up_axis]
    print(f"clip      {clip.path}")
    print(f"frames    {clip.n_frames} at {1.0 / clip.frame_time:.2f} Hz, {clip.duration:.3f} s")
    print(f"units     {anat.units} ({clip.length_scale:g} m per file unit)")
    print(f"stature   {anat.stature:.3f} m, up axis {up}")
    print(f"bodies    {model.n_bodies}, simulated DOFs {model.n_dofs}, constraint rows {model.n_constraints}")
    if anat.humanoid:  # docs/body-model.md, "What the body depends on"
        print(
            "shapes    "
            + (
                "built on the zero pose (the skeleton alone)"
                if anat.shape_frame is None
                else f"built on frame {anat.shape_frame + 1}, the most upright (the zero pose does "
                "not stand): a part of the clip without it gets another body"
            )
        )
    total = float(np.sum(model.mass))
    source = (
        ("given" if character.options.body_mass is not None else f"BMI {total / anat.stature**2:.0f} at the stature")
        if anat.humanoid
        else "polyhedra at 1000 kg/m^3"
    )
    segments = f", {character.options.sex} de Leva segments" if anat.humanoid else ""
    print(f"mass      {total:.2f} kg total ({source}{segments})")
    for w in character.warnings:
        print(f"warning   {w}")
    print()
    print(_table(rows, ["joint", "parent", "segment", "mass kg", "DOFs", "channels"]))
    return 0


class _Stages:
    """One stderr line as each stage of a long command begins, with the seconds since the
    command started (``neuromotor simulate: [3.1 s] simulating ...``). Shown when stderr is a
    terminal (or ``NEUROMOTOR_PROGRESS=1``), so that captured stderr of a failing command stays
    its one error line; never with --quiet."""

    def __init__(self, command: str, quiet: bool = False):
        import time

        shown = os.environ.get("NEUROMOTOR_PROGRESS", "").strip().lower()
        if shown in ("1", "true", "yes", "on"):
            tty = True
        elif shown in ("0", "false", "no", "off"):
            tty = False
        else:
            tty = bool(getattr(sys.stderr, "isatty", lambda: False)())
        self._clock, self.command, self.quiet = time.perf_counter, command, bool(quiet) or not tty
        self._t0 = self._clock()

    def __call__(self, text: str) -> None:
        if not self.quiet:
            print(f"neuromotor {self.command}: [{self._clock() - self._t0:5.1f} s] {text}", file=sys.stderr, flush=True)


def cmd_idyn(args) -> int:
    import jax

    from neuromotor.errors import UserError
    from neuromotor.physics.inverse import idyn_arrays

    if not jax.config.jax_enable_x64:  # type: ignore[attr-defined]  # inverse dynamics is float64 only
        raise UserError("JAX runs with x64 off (JAX_ENABLE_X64 is set to false): inverse dynamics is float64; unset it")
    from neuromotor.studies.simulate import save_npz_atomic

    stage = _Stages("idyn", getattr(args, "quiet", False))
    stage(f"loading clip {args.clip or '(embedded default)'}")
    character, traj = _load(args)
    for line in character.warnings:
        print(f"neuromotor idyn: warning: {line}", file=sys.stderr)
    clip = character.clip
    times = np.arange(clip.n_frames) * clip.frame_time
    stage(f"inverse dynamics of {len(times)} frames (compiling on first use)")
    arrays = idyn_arrays(character.model, traj, times)
    arrays["joint_names"] = np.array(character.model.joint_names)
    stage(f"writing {args.output}")
    save_npz_atomic(args.output, arrays)
    print(
        f"wrote {args.output}: {len(times)} frames, {len(arrays['dof_names'])} DOFs, "
        f"max Eq. 3 residual {arrays['kkt_residual'].max():.2e}"
    )
    if getattr(args, "opensim_dir", None):
        from neuromotor.io.opensim import write_idyn_storage

        _wrote_all(write_idyn_storage(args.opensim_dir, character, arrays))
    return 0


def _wrote_all(paths: dict, stream=None) -> None:
    print("wrote " + ", ".join(str(p) for p in paths.values()), file=stream or sys.stdout)


def _sim_config(args):
    """The config of ``simulate``: the file's (or the default hit), with the command line's
    gains, clip and body options over it."""
    import dataclasses

    from neuromotor.config import DEFAULT_HIT, SimulationConfig, load_simulation_config

    if args.config:
        cfg = load_simulation_config(args.config)
    else:
        cfg = SimulationConfig(perturbations=[DEFAULT_HIT], duration=3.0, source="<default>")
    given = {key: getattr(args, key, None) for key in ("clip", "units", "up_axis", "stature", "body_mass", "sex")}
    if getattr(args, "simulate_extremities", None):
        given["simulate_extremities"] = True
    cfg = dataclasses.replace(cfg, **{k: v for k, v in given.items() if v is not None})
    return cfg.with_gains(args.ks, args.kd)


def cmd_simulate(args) -> int:
    from neuromotor.studies.record import run_arrays
    from neuromotor.studies.simulate import config_character, prepare, run, save_npz_atomic

    stage = _Stages("simulate", getattr(args, "quiet", False))
    cfg = _sim_config(args)
    stage(f"loading clip {cfg.clip or '(embedded default)'}")
    character, traj = config_character(cfg)
    stage("inverse dynamics of the reference motion (compiling on first use)")
    setup = prepare(cfg, character, traj)
    for line in setup.warnings:
        print(f"neuromotor simulate: warning: {line}", file=sys.stderr)
    stage(
        f"simulating {setup.options.n_steps} steps of {setup.options.h * 1000:.2f} ms, perturbed and unperturbed "
        "(compiling on first use)"
    )
    result = run(setup)
    stage(f"writing {args.output}")
    arrays = run_arrays(setup, result, residuals=True if args.residuals else None)
    save_npz_atomic(args.output, arrays)
    if args.json:
        print(json.dumps(metrics_json(result.metrics), indent=2))
    else:
        m = result.metrics
        print(
            f"wrote {args.output}: peak deviation {m['peak_deviation_deg']:.2f} deg at "
            f"{m['time_of_peak_s']:.2f} s, recovery {m['recovery_time_s']:.2f} s, "
            f"unperturbed RMS error {m['unperturbed_rms_error_deg']:.2f} deg"
        )
    if getattr(args, "opensim_dir", None):
        from neuromotor.io.opensim import write_run_storage

        # With --json, stdout stays one JSON document.
        _wrote_all(write_run_storage(args.opensim_dir, character, arrays), sys.stderr if args.json else sys.stdout)
    return 0


def _wrote(path) -> int:
    print(f"wrote {path}")
    return 0


def cmd_render(args) -> int:
    from neuromotor.viz.render import render_run

    quiet = getattr(args, "quiet", False)
    render_run(args.run, args.output, frames=args.frames, progress=not quiet, stage=_Stages("render", quiet))
    return _wrote(args.output)


def cmd_plot(args) -> int:
    from neuromotor.viz.render import plot_run

    plot_run(args.run, args.output)
    return _wrote(args.output)


def cmd_view(args) -> int:
    from neuromotor.viz.html import write_viewer

    write_viewer(args.run, args.output)
    return _wrote(args.output)


def cmd_sweep(args) -> int:
    from neuromotor import distributed
    from neuromotor.studies.sweep import sweep_from_config

    procs = distributed.from_args(args)  # bad multi-process options: exit 2 before anything starts
    if (args.local_processes or 1) > 1:  # N copies of this command, one rank each
        argv = distributed.without_option(args.argv, "--local-processes")
        return distributed.launch_local(argv, args.local_processes, args.process_timeout)
    if procs is not None:
        distributed.initialize(procs)
    fitted = tuple(args.fitted) if args.fitted else args.fitted_json
    result, files = sweep_from_config(
        args.config, args.output, chunk=args.chunk, inner_batch=args.inner_batch, fitted=fitted, progress=not args.quiet
    )
    if distributed.is_lead():  # the other processes computed their shares; process 0 wrote the table
        bad = sum(r["diverged"] for r in result.rows)
        print(f"{len(result.rows)} runs ({bad} diverged); wrote " + ", ".join(str(f) for f in files.values()))
    return 0


def cmd_fit(args) -> int:
    from neuromotor.studies.fit import FitError, calibrate, load_calibration, write_synthetic_target

    try:
        if args.write_synthetic:
            path = write_synthetic_target(
                args.config, *_truth(args.write_synthetic), noise_deg=args.noise_deg, seed=args.seed
            )
            print(f"wrote {path}")
            return 0
        cal = load_calibration(args.config, solver=args.solver)
        for line in (cal.not_fitted, cal.converted):
            if line:
                print(f"neuromotor fit: {line}", file=sys.stderr)
        res, doc = calibrate(cal, args.output, progress=not args.quiet)
    except FitError as e:  # the fit ran and failed: not bad input, a status of its own
        print(f"neuromotor fit: error: {e}", file=sys.stderr)
        return 3
    from neuromotor.studies.fit.parameters import UNITS

    fitted = ", ".join(f"{n} = {v:.6g} +- {res.standard_errors[n]:.3g} {UNITS[n]}" for n, v in res.values.items())
    print(
        f"{res.solver}: {fitted} (corr {res.correlation:+.2f}); residual {res.residual_norm:.4g}, "
        f"{res.iterations} iterations, {res.wall_time_s:.1f} s; wrote {args.output}/fit.json, fit.png"
    )
    for row in doc.get("leave_one_out", []):
        errs = ", ".join(_rms_text(e) for e in row["predicted"])
        print(f"leave-one-out: case {row['case']} predicted by a fit on the others: RMS {errs}")
    if not all(res.identifiable.values()):
        print(f"neuromotor fit: warning: {res.identifiability}", file=sys.stderr)
    if not res.converged:
        print(f"neuromotor fit: error: {res.status}: {res.message}", file=sys.stderr)
        return 3
    if res.status != "converged":  # converged (loss flat): a success, said so
        print(f"neuromotor fit: {res.message}", file=sys.stderr)
    return 0


def _rms_text(e: dict) -> str:
    """One target's error of a fit report: ``head: angle about left 1.2 deg (0.8 sd)``."""
    parts = ([f"{e['rms']:.4g} {e['unit']}"] if e["rms"] is not None else []) + (
        [f"{e['rms_sd']:.3g} sd"] if e["rms_sd"] is not None else []
    )
    text = parts[0] + (f" ({parts[1]})" if len(parts) > 1 else "") if parts else "n/a"
    return f"{e['target']} {text}"


def _truth(values) -> tuple[float | None, float | None, dict[str, float]]:
    """(ks, kd, values) of --write-synthetic: two bare numbers are (ks, kd)."""
    named: dict[str, float] = dict(v for v in values if isinstance(v, tuple))
    bare = [v for v in values if not isinstance(v, tuple)]
    if bare and (named or len(bare) != 2):
        from neuromotor.errors import UserError

        raise UserError("--write-synthetic takes KS KD, or NAME=VALUE for each fitted parameter, not a mix")
    return (*bare, named) if bare else (None, None, named)


def cmd_experiment(args) -> int:
    from neuromotor.studies.experiments import run_experiment

    numbers = run_experiment(args.config, output=args.output, progress=not args.quiet)
    print(json.dumps(_strict_json(numbers), indent=2, default=float))
    return 0


def cmd_export_bvh(args) -> int:
    from neuromotor.io.export import export_bvh

    export_bvh(args.run, args.output)
    return _wrote(args.output)


def cmd_export_gltf(args) -> int:
    from neuromotor.io.gltf import Layout, export_gltf

    export_gltf(args.run, args.output, Layout(args.layout))
    return _wrote(args.output)


def cmd_demo(args) -> int:
    out = pathlib.Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    ns = argparse.Namespace(config=None, ks=None, kd=None, json=False, output=out / "run.npz")
    cmd_simulate(ns)
    from neuromotor.viz.render import plot_run, render_run

    for name in ("filmstrip.png", "video.mp4"):
        render_run(out / "run.npz", out / name)
        print(f"wrote {out / name}")
    plot_run(out / "run.npz", out / "deviation.png")
    print(f"wrote {out / 'deviation.png'}")
    return 0


def cmd_bench(args) -> int:
    from neuromotor.studies.bench import run_from_args

    return run_from_args(args)


def _flat(prefix: str, value, out: list) -> None:
    """Nested JSON values as (dotted key, text) rows, lists of dicts numbered."""
    if isinstance(value, dict):
        if not value:
            out.append((prefix, "{}"))
        for k, v in value.items():
            _flat(f"{prefix}.{k}" if prefix else str(k), v, out)
    elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
        for i, v in enumerate(value):
            _flat(f"{prefix}[{i}]", v, out)
    elif isinstance(value, list):
        out.append(
            (prefix, "[" + ", ".join(f"{v:.6g}" if isinstance(v, float) else json.dumps(v) for v in value) + "]")
        )
    elif isinstance(value, float):
        out.append((prefix, f"{value:.6g}"))
    else:
        out.append((prefix, "null" if value is None else str(value)))


def _strict_json(value):
    """NaN and infinities as null, recursively (strict JSON)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _strict_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_strict_json(v) for v in value]
    return value


def cmd_info(args) -> int:
    from neuromotor.studies.simulate import read_run_info

    info = read_run_info(args.run)
    if args.json:
        print(json.dumps(_strict_json(info), indent=2, default=str))
        return 0
    print(f"run       {info['file']}")
    # The residuals (issue 38, docs/residuals.md) only where the run recorded them.
    sections = (("provenance", "provenance"), ("metrics", "metrics")) + (
        (("residuals (the capture's inverse dynamics with the ground; docs/residuals.md)", "residuals"),)
        if info.get("residuals") is not None
        else ()
    )
    for title, key in sections:
        print()
        if info[key] is None:
            print(f"{title}: not recorded (a run file from an older neuromotor)")
            continue
        print(f"{title}:")
        rows: list = []
        _flat("", info[key], rows)
        width = max(len(k) for k, _ in rows) if rows else 0
        for k, v in rows:
            print(f"  {k.ljust(width)}  {v}")
    print()
    arrays = info["arrays"]
    shown = ", ".join(f"{k} {tuple(v)}" for k, v in arrays.items() if k in ("time", "theta"))
    print(f"arrays: {len(arrays)} ({shown}, ...)")
    return 0


def cmd_export_mjcf(args) -> int:
    from neuromotor.io.mjcf import export_mjcf

    character, _ = _load(args)
    export_mjcf(character, args.output, timestep=args.timestep)
    return _wrote(args.output)


def cmd_export_osim(args) -> int:
    from neuromotor.io.opensim import export_osim

    character, _ = _load(args)
    export_osim(character, args.output)
    return _wrote(args.output)


def _units_arg(text: str):
    from neuromotor.model.anatomy import UNIT_CHOICES

    if text == "auto" or text in UNIT_CHOICES:
        return text
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be auto, {', '.join(UNIT_CHOICES)} or a positive number, got {text!r}")
    return value


def _number_arg(text: str, low: float, strict: bool, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and (value > low if strict else value >= low)):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def _truth_arg(text: str):
    """A number >= 0, or NAME=NUMBER (a fitted parameter's known value)."""
    name, _, num = text.rpartition("=")
    return (name, _gain_arg(num)) if name else _gain_arg(num)


def _gain_arg(text: str) -> float:
    """--ks/--kd: finite and >= 0 (a negative stiffness pushes away from the mocap)."""
    return _number_arg(text, 0.0, False, "a finite number >= 0")


def _positive_arg(text: str) -> float:
    return _number_arg(text, 0.0, True, "a finite number > 0")


def _nonneg_arg(text: str) -> float:
    return _number_arg(text, 0.0, False, "a finite number >= 0")


def _up_arg(text: str):
    if text == "auto":
        return None
    if text in ("0", "1", "2"):
        return int(text)
    raise argparse.ArgumentTypeError(f"must be auto, 0, 1 or 2, got {text!r}")


class _Parser(argparse.ArgumentParser):
    """Argument errors as one line (``neuromotor simulate: error: argument --ks: ...``), exit 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _count_arg(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


RUN_HELP = "RUN.npz written by simulate"
OPENSIM_HELP = "also write OpenSim files to this folder (docs/opensim.md): model.osim, "
PROGRESS_HELP = "no progress bar on stderr (--no-progress is the same)"


def _body_args(sp, defaults=True) -> None:
    """The clip options: units, up axis and the body model (``defaults=False``: None unless given)."""
    d = (lambda v: v) if defaults else (lambda v: None)
    sp.add_argument(
        "--units",
        default=d("auto"),
        type=_units_arg,
        help="length unit of the file: auto (from the stature the long bones give), m, cm, mm, "
        "in, cmu (CMU's 1/0.45 inch), ft, dm, or metres per file unit",
    )
    sp.add_argument(
        "--up-axis",
        default=d("auto"),
        type=_up_arg,
        help="world up axis: auto (from the motion), 0 (X), 1 (Y) or 2 (Z); gravity along -up",
    )
    sp.add_argument("--stature", type=_positive_arg, default=None, help="stature in metres (default: estimated)")
    sp.add_argument("--body-mass", type=_positive_arg, default=None, help="body mass in kg (default: BMI 22)")
    sp.add_argument(
        "--sex", choices=("average", "male", "female"), default=d("average"), help="column of de Leva's segment table"
    )
    sp.add_argument(
        "--simulate-extremities",
        action="store_true",
        default=d(False),
        help="simulate fingers, toes and face joints as bodies",
    )


def _command(sub, name: str, func, help: str, first=None, output=None, **output_kw):
    """A subcommand: its positional argument ``first`` = (name, help, nargs) and ``-o`` (help text)."""
    sp = sub.add_parser(name, help=help)
    if first is not None:
        arg, text, nargs = first
        sp.add_argument(arg, help=text, **({"nargs": nargs, "default": None} if nargs else {}))
    if output is not None:
        sp.add_argument("-o", "--output", help=output, **(output_kw or {"required": True}))
    sp.set_defaults(func=func)
    return sp


def _clip_command(sub, name, func, help, output=None):
    sp = _command(sub, name, func, help, ("clip", "BVH file (default: embedded clip)", "?"), output)
    _body_args(sp)
    return sp


def _add_clip_commands(sub) -> None:
    sp = _clip_command(sub, "inspect", cmd_inspect, "bodies, masses, DOFs of a clip")
    sp.add_argument("--json", action="store_true", help="print the model as JSON (README: file contracts)")
    sp = _clip_command(
        sub,
        "idyn",
        cmd_idyn,
        "inverse dynamics (Eq. 3) on every frame",
        "NPZ file of joint angles, torques (N m), root wrench",
    )
    sp.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    sp.add_argument("--opensim-dir", default=None, help=OPENSIM_HELP + "motion.mot and inverse_dynamics.sto")
    sp = _command(
        sub,
        "simulate",
        cmd_simulate,
        "perturbed forward simulation (Eq. 2)",
        ("config", "TOML config (default: the embedded clip and a 400 N chest push)", "?"),
        "RUN.npz: the perturbed and unperturbed runs",
    )
    sp.add_argument("--ks", type=_gain_arg, help="stiffness gain, 1/s^2 (>= 0)")
    sp.add_argument("--kd", type=_gain_arg, help="damping gain, 1/s (>= 0)")
    sp.add_argument("--clip", default=None, help="BVH file (overrides the config's clip)")
    _body_args(sp, defaults=False)
    sp.add_argument("--json", action="store_true", help="print the recovery metrics as JSON (deg, s)")
    sp.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    sp.add_argument(
        "--opensim-dir",
        default=None,
        help=OPENSIM_HELP + "perturbed.mot, unperturbed.mot and, with the capture's residuals "
        "(docs/residuals.md), external_loads.sto/.xml and residuals.sto",
    )
    sp.add_argument(
        "--residuals",
        action="store_true",
        help="also solve the capture's ground reaction forces and the root residuals they leave "
        "(docs/residuals.md; always with a ground)",
    )


def _add_run_commands(sub) -> None:
    sp = _command(
        sub,
        "render",
        cmd_render,
        "filmstrip PNG or MP4/GIF of a run",
        ("run", RUN_HELP, None),
        "PNG (filmstrip), MP4 or GIF (side-by-side video)",
    )
    sp.add_argument("--frames", type=_count_arg, default=6, help="panels of the filmstrip per row")
    sp.add_argument("--quiet", action="store_true", help="no progress lines or bar on stderr")
    _command(
        sub,
        "plot",
        cmd_plot,
        "PNG plots of a run: deviation and joint angles vs time",
        ("run", RUN_HELP, None),
        "PNG of the deviation (deg) and joint angles against time (s)",
    )
    _command(
        sub,
        "view",
        cmd_view,
        "interactive 3-D viewer of a run: one self-contained HTML page",
        ("run", RUN_HELP, None),
        "HTML page (opens offline in a browser; docs/viewer.md)",
    )


def _add_sweep_command(sub) -> None:
    sp = _command(
        sub,
        "sweep",
        cmd_sweep,
        "batch grid of perturbed runs (sharded over devices) -> CSV + plots",
        ("config", "TOML config with a [sweep] table", None),
        "folder (default: the config's sweep.output)",
        default=None,
    )
    sp.add_argument("--chunk", type=_count_arg, help="runs per device call")
    sp.add_argument("--inner-batch", type=_count_arg, help="rollouts vmapped together inside each shard")
    sp.add_argument(
        "--fitted", type=_gain_arg, nargs=2, metavar=("KS", "KD"), help="fitted pair to mark on the gains map"
    )
    sp.add_argument("--fitted-json", help="JSON file with the fitted ks and kd")
    sp.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true", help=PROGRESS_HELP)
    from neuromotor.distributed import add_arguments

    add_arguments(sp)
    _command(
        sub,
        "export-bvh",
        cmd_export_bvh,
        "write the perturbed motion as BVH",
        ("run", RUN_HELP, None),
        "BVH in the source clip's skeleton, channel orders and units",
    )
    sp = _command(
        sub,
        "export-gltf",
        cmd_export_gltf,
        "write the bodies and both motions as glTF 2.0",
        ("run", RUN_HELP, None),
        "GLB (binary) or GLTF (JSON, buffer embedded) file; docs/gltf.md",
    )
    sp.add_argument(
        "--layout",
        choices=("ghost", "shared"),
        default="ghost",
        help="unperturbed motion on a translucent second character (ghost) or on the same one (shared)",
    )


def _add_study_commands(sub) -> None:
    sp = _command(
        sub,
        "fit",
        cmd_fit,
        "calibrate the gain pair (ks, kd) (or the [fit] parameters: reflex gains and "
        "delays too) to a target response -> fit.json + fit.png",
        ("config", "TOML config with a [fit] table", None),
        "folder for fit.json and fit.png",
        default="out/fit",
    )
    sp.add_argument(
        "--solver",
        default=None,
        help="override fit.solver (optimistix_lm, optimistix_gn, optimistix_bfgs, jaxopt_lm, jaxopt_lbfgs)",
    )
    sp.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true", help=PROGRESS_HELP)
    sp.add_argument(
        "--write-synthetic",
        nargs="+",
        type=_truth_arg,
        metavar="VALUE",
        help="instead of fitting, simulate the config's target file at these values: KS KD, or "
        "NAME=VALUE for each of the [fit] parameters (e.g. reflex_gain=130 reflex_delay=0.05)",
    )
    sp.add_argument(
        "--noise-deg",
        type=_nonneg_arg,
        default=0.0,
        help="with --write-synthetic: Gaussian noise added to the target angles (deg)",
    )
    sp.add_argument("--seed", type=int, default=0, help="with --write-synthetic: random seed of the noise")
    sp = _command(
        sub,
        "experiment",
        cmd_experiment,
        "run one of the paper's experiments (arm, full_body, contrast)",
        ("config", "TOML config with an [experiment] table whose kind picks the experiment", None),
        "folder for run*.npz, metrics.json and the figures (default: the config's experiment.output)",
        default=None,
    )
    sp.add_argument("--quiet", "--no-progress", dest="quiet", action="store_true", help=PROGRESS_HELP)


def _add_other_commands(sub) -> None:
    sp = _command(
        sub,
        "bench",
        cmd_bench,
        "speed: steps/s, real-time factor, batch throughput, vs MuJoCo",
        ("clip", "BVH clip (default: the embedded 19-joint clip)", "?"),
    )
    _body_args(sp)
    sp.add_argument(
        "--solver", choices=("nullspace", "tree", "dense"), default="nullspace", help="KKT solver of Eq. 2 to time"
    )
    sp.add_argument("--sizes", type=_count_arg, nargs="+", default=[1, 8, 64, 256], help="vmap batch sizes")
    sp.add_argument("--repeats", type=_count_arg, default=5, help="timed repeats; the best is reported")
    sp.add_argument("--idyn", nargs="*", default=[], help="clips for the inverse-dynamics figure")
    sp.add_argument("--plot", default=None, help="PNG of throughput against batch size")
    sp.add_argument("--json", default=None, help="write all figures as JSON")
    sp.add_argument("--no-dense", action="store_true", help="skip the dense reference path")
    sp.add_argument("--no-mjx", action="store_true", help="skip MuJoCo MJX (optional extra; compiles six programs)")
    sp.add_argument("--no-free", action="store_true", help="skip the free root standing on the ground")
    sp.add_argument(
        "--free-only", action="store_true", help="only the free root standing on the ground, beside the driven root"
    )
    sp = _clip_command(
        sub,
        "export-mjcf",
        cmd_export_mjcf,
        "write the character as MuJoCo MJCF (hinges, position servos)",
        "MJCF XML file",
    )
    sp.add_argument("--timestep", type=_positive_arg, default=1.0 / 120.0, help="MuJoCo time step (s, > 0)")
    _clip_command(
        sub,
        "export-osim",
        cmd_export_osim,
        "write the character as an OpenSim model (bodies, custom joints, Y-up)",
        "OpenSim .osim file",
    )
    sp = _command(
        sub,
        "info",
        cmd_info,
        "what made a run: version, clip and its SHA-256, resolved config, metrics",
        ("run", RUN_HELP, None),
    )
    sp.add_argument("--json", action="store_true", help="print it as JSON")
    _command(
        sub,
        "demo",
        cmd_demo,
        "main job: simulate the default hit on the embedded clip and render it",
        output="folder for run.npz, filmstrip.png, video.mp4, deviation.png",
        default="out/demo",
    )


def build_parser() -> argparse.ArgumentParser:
    from neuromotor import __version__

    p = _Parser(prog="neuromotor", description=__doc__.split("\n")[0])
    p.add_argument("--version", action="version", version=f"neuromotor {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (_add_clip_commands, _add_run_commands, _add_sweep_command, _add_study_commands, _add_other_commands):
        add(sub)
    return p


def _io_paths(args) -> tuple[list, list, list]:
    """(inputs, output files, output folders) of a command, for :func:`outputs.check_outputs`.
    Reads config files (cheap) but computes nothing."""
    from neuromotor.io.outputs import inputs_of_run

    cmd, out = args.command, getattr(args, "output", None)
    clip = getattr(args, "clip", None)
    if cmd in ("export-mjcf", "export-osim"):
        return [clip], [out], []
    if cmd in ("idyn", "simulate"):
        return _clip_run_paths(args)
    if cmd in ("render", "plot", "export-gltf", "view"):
        return [args.run], [out], []
    if cmd == "export-bvh":
        return [args.run, *inputs_of_run(args.run)], [out], []
    if cmd == "bench":
        return [clip, *args.idyn], [args.plot, args.json], []
    if cmd == "demo":
        assert out is not None  # --output has a default
        d = pathlib.Path(out)
        return [], [d / n for n in ("run.npz", "filmstrip.png", "video.mp4", "deviation.png")], [d]
    if cmd == "experiment":
        from neuromotor.config import load_experiment

        cfg, exp = load_experiment(args.config)
        return [args.config, cfg.clip], [], [pathlib.Path(out) if out else exp.output]
    if cmd == "sweep":
        from neuromotor.config import load_sweep_config

        cfg, spec = load_sweep_config(args.config)
        d = pathlib.Path(out or spec.output or pathlib.Path("out") / "sweep" / pathlib.Path(args.config).stem)
        files = [d / n for n in ("sweep.csv", "sweep.png", "gains_map.png")]
        return [args.config, cfg.clip, args.fitted_json], files, [d]
    if cmd == "fit":
        return _fit_paths(args)
    return [], [], []


def _clip_run_paths(args) -> tuple[list, list, list]:
    """``idyn`` and ``simulate``: their output and, with --opensim-dir, the OpenSim files."""
    clip, folder = getattr(args, "clip", None), getattr(args, "opensim_dir", None)
    names = ("motion.mot", "inverse_dynamics.sto") if args.command == "idyn" else ("perturbed.mot", "unperturbed.mot")
    files = [pathlib.Path(folder) / n for n in ("model.osim", *names)] if folder is not None else []
    inputs = [clip] if args.command == "idyn" else [args.config, clip, _sim_config(args).clip]
    return inputs, [args.output, *files], [folder]


def _fit_sim_config(args):
    """The fit config's path, its TOML table and the simulation config it holds."""
    from neuromotor.config import read_toml, simulation_config

    path = pathlib.Path(args.config)
    data = read_toml(path)
    return path, data, simulation_config(data, str(path), path.parent)


def _fit_paths(args) -> tuple[list, list, list]:
    """The fit's config, clip and target file; it writes fit.json and fit.png, or (with
    --write-synthetic) the target file."""
    from neuromotor.config import fit_spec

    path, data, cfg = _fit_sim_config(args)
    if args.write_synthetic:  # the target table is checked by the writer
        target = data.get("fit", {}).get("target", {}) if isinstance(data.get("fit"), dict) else {}
        file = target.get("file") if isinstance(target, dict) else None
        return [args.config, cfg.clip], [path.parent / file if isinstance(file, str) else None], []
    d = pathlib.Path(args.output)
    targets = fit_spec(data, cfg, path.parent).targets
    return [args.config, cfg.clip, *(f for t in targets for f in t.paths)], [d / "fit.json", d / "fit.png"], [d]


def _preflight(args) -> None:
    """Before any computation: every output can be written and overwrites no input."""
    from neuromotor.io.outputs import check_outputs

    inputs, files, folders = _io_paths(args)
    check_outputs(files=files, folders=folders, inputs=inputs)


def _free_root_run(args) -> bool:
    """A single free-root trajectory: ``bench --free-only``, or ``simulate`` or ``fit`` of a
    config with ``[sim] root = "free"`` (reads the config, computes nothing; a config the
    command will refuse is not one)."""
    from neuromotor.errors import UserError

    if args.command == "bench":
        return bool(args.free_only)
    try:
        if args.command == "simulate":
            return _sim_config(args).root == "free"
        if args.command == "fit":
            return _fit_sim_config(args)[2].root == "free"
    except (UserError, OSError):
        return False
    return False


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # for `sweep --local-processes`
    from neuromotor.compiler import enable_compile_cache, one_runtime_thread, use_cpu_cores

    if args.command != "bench":  # bench reports compile times: it compiles for real
        enable_compile_cache()  # persistent XLA cache: a second `simulate` loads instead of compiling
    from neuromotor.errors import UserError

    try:
        # Before JAX starts: batches and sweeps split over the cores; single runs on one device,
        # a free root's with one runtime thread (docs/benchmarks.md, "Thread hand-offs").
        if _free_root_run(args):
            one_runtime_thread()
        use_cpu_cores(split=args.command in ("sweep", "experiment") or (args.command == "bench" and not args.free_only))
        _preflight(args)  # SIGINT/SIGTERM while an output is being written: atomic.atomic_path
        status = args.func(args)
        sys.stdout.flush()  # a closed pipe shows here, not at exit
        return status
    except KeyboardInterrupt:
        print(f"neuromotor {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `neuromotor inspect | head`: the reader left, nothing is wrong
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as e:  # a directory as the clip, no permission, ...: name the file
        where = f"{e.filename}: " if e.filename else ""
        print(f"neuromotor {args.command}: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except UserError as e:  # bad input; anything else is a bug and shows its traceback
        print(f"neuromotor {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
