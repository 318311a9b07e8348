"""The paper's experiments (Section 6), each driven by a config file in ``configs/``.

* **Arm** (:func:`arm`): every joint except one arm is driven along the mocap
  (``sim.driven_joints``); a pulse at the forearm deflects the free arm, which returns to the
  captured motion while the rest of the body stays exactly on it.
* **Full body** (:func:`full_body`): the whole body is simulated and hit at the chest or head;
  Figure 2 as a filmstrip (original above, perturbed below) and a video, via
  :func:`neuromotor.viz.render.render_run`.
* **High-gain contrast** (:func:`contrast`): the same hit under several controllers, by default
  the paper's feedforward + low-gain feedback, a high-gain PD tracker without feedforward
  (Zordan & Hodgins 2002) and, to show why the tracker needs its high gains, the same PD tracker
  at the low gains; deviation curves, tracking error and recovery numbers.

Every experiment writes into its output folder ``run*.npz`` (the RUN.npz contract),
``metrics.json`` and PNG figures, all through temporary files. ``neuromotor experiment CONFIG``
(:func:`run_experiment`) runs the one a config names. The ``[experiment]`` table (parsed by
:func:`neuromotor.config.experiment_spec`)::

    [experiment]
    kind = "arm"                  # arm | full_body | contrast
    output = "out/exp_arm"        # relative to the config file
    frames = 6                    # filmstrip panels
    video = "video.gif"           # full_body: "" for none; .mp4 or .gif
    arm = ["LeftShoulder", "LeftElbow", "LeftWrist"]   # arm: the free joints to plot
    magnitudes = [100.0, 200.0]   # contrast: also sweep these magnitudes (N or N s; a [ball]: speeds, m/s)

    [[experiment.controller]]     # contrast: any number; default: the three described above
    label = "PD tracker, high gain"
    controller = "pd"             # neuromotor | pd
    ks = 10000.0
    kd = 200.0
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any

import numpy as np

from neuromotor.config.parse import experiment_spec, load_experiment
from neuromotor.config.specs import (
    DEFAULT_CONTRAST,
    EXPERIMENT_KINDS as KINDS,
    ExperimentSpec,
    GainSetting,
    SimulationConfig,
    onset,
)
from neuromotor.errors import ConfigError
from neuromotor.io.tables import write_json as _write_json
from neuromotor.studies import metrics as mx
from neuromotor.studies.gains import gains_for
from neuromotor.viz.figures import pyplot, save_png as save_figure

__all__ = [
    "DEFAULT_CONTRAST",
    "KINDS",
    "RUNNERS",
    "arm",
    "contrast",
    "experiment_spec",
    "full_body",
    "load_experiment",
    "run_experiment",
    "write_json",
]


def write_json(obj: Any, path) -> pathlib.Path:
    """metrics.json: indented, NaN kept as NaN (a recovery time that never came)."""
    return _write_json(path, obj, strict=False)


def _hit_span(cfg: SimulationConfig) -> tuple[float, float]:
    """Clip seconds the hit spans: from its :func:`~neuromotor.config.specs.onset` to the end of
    the last push (an impulse: its step; a ball: one step from its launch, its contact comes later)."""
    start = onset(cfg.perturbations, cfg.ball)
    ends = [p.acting(cfg.h)[1] for p in cfg.perturbations]
    return start, max(ends, default=start + cfg.h)


def _hit(cfg: SimulationConfig) -> tuple[dict, str]:
    """The hit as configured (metrics.json) and as a title names it."""
    if cfg.perturbations:
        p = cfg.perturbations[0]
        return dict(p), f"{p.label()} {p.place}"
    assert cfg.ball is not None  # the parser requires a perturbation or a ball
    aim = f" at {cfg.ball.target}" if cfg.ball.target is not None else ""
    return {"kind": "ball", **dict(cfg.ball)}, cfg.ball.label() + aim


def _simulate(
    cfg: SimulationConfig, out: pathlib.Path, name: str = "run.npz", setting: GainSetting | None = None, setup=None
):
    """One perturbed + unperturbed pair, saved as RUN.npz; returns (setup, result, npz path)."""
    from neuromotor.studies.record import run_arrays
    from neuromotor.studies.simulate import prepare, run, save_npz_atomic

    if setup is None:
        setup = prepare(cfg)
    if setting is not None:
        setup = dataclasses.replace(setup, gains=gains_for(setup.gains, setting))
    result = run(setup, check=False)
    path = save_npz_atomic(out / name, run_arrays(setup, result))
    return setup, result, path


def _render(npz, out: pathlib.Path, exp: ExperimentSpec, video: bool) -> dict[str, str]:
    """Filmstrip (and video) when the renderer is available; never fails the experiment."""
    files = {}
    try:
        from neuromotor.viz.render import render_run
    except ImportError as e:  # renderer not installed in this environment
        return {"render_skipped": str(e)}
    try:
        files["filmstrip"] = str(
            render_run(npz, out / "filmstrip.png", frames=exp.frames, progress=False) or out / "filmstrip.png"
        )
        if video and exp.video:
            files["video"] = str(render_run(npz, out / exp.video, progress=False) or out / exp.video)
    except Exception as e:  # e.g. no off-screen OpenGL: keep the numbers and plots
        files["render_error"] = f"{type(e).__name__}: {e}"
    return files


def _dof_groups(model, names):
    return {n: [i for i, d in enumerate(model.dof_names) if d.split(".")[0] == n] for n in names}


def arm(cfg: SimulationConfig, exp: ExperimentSpec) -> dict:
    """The arm experiment; returns the numbers written to ``metrics.json``."""
    out = exp.output
    setup, result, npz = _simulate(cfg, out)
    model = setup.model
    groups = _dof_groups(model, exp.arm)
    missing = [n for n, dofs in groups.items() if not dofs]
    if missing:
        raise ConfigError(f"{cfg.source}: field 'experiment.arm': no simulated joint named {missing[0]!r}")
    arm_dofs = sorted(i for dofs in groups.values() for i in dofs)
    rest = [i for i in range(model.n_dofs) if i not in arm_dofs]
    from neuromotor.studies.simulate import deviation_curve

    pert, base = np.asarray(result.perturbed.theta), np.asarray(result.unperturbed.theta)
    t = np.asarray(result.perturbed.time)
    dev_arm = deviation_curve(setup, result.perturbed, result.unperturbed, mx.dof_joints(model, arm_dofs))
    start, end = _hit_span(cfg)
    if cfg.metric == "euler":  # the largest change of one Euler angle
        peak_of = lambda dofs: float(np.rad2deg(np.abs(pert[:, dofs] - base[:, dofs]).max()))
    else:  # the largest rotation change of one of the joints turned by these DOFs
        change = np.asarray(
            mx.joint_angle_changes_deg(model, result.perturbed.states.quat, result.unperturbed.states.quat)
        )
        peak_of = lambda dofs: float(change[:, mx.joint_rows(model, mx.dof_joints(model, dofs))].max())
    numbers = {
        "arm": mx.recovery_metrics(t, dev_arm, start),
        "all_dofs": result.metrics,
        "rest_of_body_max_deviation_deg": peak_of(rest) if rest else 0.0,
        "per_joint_peak_deg": {n: peak_of(d) for n, d in groups.items()},
        "driven_joints": list(cfg.driven_joints),
    }
    plt = pyplot()
    rows = len(groups) + 1
    fig, axes = plt.subplots(rows, 1, figsize=(7, 1.7 * rows + 0.6), dpi=90, sharex=True)
    axes[0].plot(t, dev_arm, color="C3")
    axes[0].axvspan(start, end, color="C1", alpha=0.25, lw=0, label="hit")
    axes[0].set_ylabel("arm deviation\n(deg)")
    axes[0].legend(fontsize=7, loc="upper right")
    desired = np.asarray(setup.ref.theta[: len(t)])
    for ax, (name, dofs) in zip(axes[1:], groups.items()):
        for k, i in enumerate(dofs):
            c = f"C{k}"
            ax.plot(t, np.rad2deg(desired[:, i]), ":", color=c, lw=1)
            ax.plot(t, np.rad2deg(base[:, i]), "--", color=c, lw=1)
            ax.plot(t, np.rad2deg(pert[:, i]), "-", color=c, lw=1.4, label=model.dof_names[i].split(".")[1])
        ax.axvspan(start, end, color="C1", alpha=0.25, lw=0)
        ax.set_ylabel(f"{name}\n(deg)")
        ax.legend(fontsize=6, loc="upper right", ncol=3)
    axes[-1].set_xlabel("clip time (s)  -  solid: perturbed, dashed: unperturbed, dotted: mocap")
    fig.suptitle("Arm hit at the forearm; rest of the body driven along the mocap", fontsize=10)
    fig.tight_layout()
    numbers["files"] = {"run": str(npz), "plot": str(save_figure(fig, out / "arm.png"))}
    numbers["files"].update(_render(npz, out, exp, video=bool(exp.video)))
    write_json(numbers, out / "metrics.json")
    return numbers


def full_body(cfg: SimulationConfig, exp: ExperimentSpec) -> dict:
    """The full-body experiment (Figure 2)."""
    out = exp.output
    setup, result, npz = _simulate(cfg, out)
    from neuromotor.studies.simulate import deviation_curve

    t = np.asarray(result.perturbed.time)
    dev = deviation_curve(setup, result.perturbed, result.unperturbed)
    start, end = _hit_span(cfg)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 2.6), dpi=90)
    ax.plot(t, dev, color="C3", label="deviation from the unperturbed run")
    ax.axhline(result.metrics["recovery_threshold_deg"], color="0.5", ls=":", lw=1, label="recovery threshold")
    ax.axvspan(start, end, color="C1", alpha=0.25, lw=0, label="hit")
    ax.set(xlabel="clip time (s)", ylabel="RMS deviation (deg)")
    ax.legend(fontsize=7)
    hit, title = _hit(cfg)
    ax.set_title(f"Full body, {title}", fontsize=10)
    fig.tight_layout()
    numbers = {
        "metrics": result.metrics,
        "hit": hit,
        "files": {"run": str(npz), "deviation": str(save_figure(fig, out / "deviation.png"))},
    }
    numbers["files"].update(_render(npz, out, exp, video=True))
    write_json(numbers, out / "metrics.json")
    return numbers


def contrast(cfg: SimulationConfig, exp: ExperimentSpec, progress: bool = True) -> dict:
    """The same hit under each controller of ``exp.controllers``."""
    from neuromotor.studies.simulate import deviation_curve, prepare, tracking_curve

    out = exp.output
    base_setup = prepare(cfg)
    start, end = _hit_span(cfg)
    numbers: dict[str, Any] = {"hit": _hit(cfg)[0], "controllers": []}
    curves = []
    for i, setting in enumerate(exp.controllers):
        setup, result, npz = _simulate(cfg, out, f"run_{i}.npz", setting, setup=base_setup)
        t = np.asarray(result.perturbed.time)
        dev = deviation_curve(setup, result.perturbed, result.unperturbed)
        track = tracking_curve(setup, result.unperturbed)
        curves.append((setting, t, dev, track))
        numbers["controllers"].append(
            {
                "label": setting.name,
                "controller": setting.controller,
                "ks": setting.ks,
                "kd": setting.kd,
                **result.metrics,
                "run": str(npz),
            }
        )
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4), dpi=90)
    for setting, t, dev, track in curves:
        axes[0].plot(t, dev, label=setting.name)
        axes[1].plot(t, track, label=setting.name)
    for ax in axes:
        ax.axvspan(start, end, color="C1", alpha=0.25, lw=0)
        ax.set_xlabel("clip time (s)")
        ax.grid(alpha=0.3)
    axes[0].set(ylabel="deviation from own unperturbed run (deg)", title="deflection and recovery")
    axes[1].set(ylabel="unperturbed run vs mocap (deg)", title="tracking error without the hit", yscale="log")
    axes[1].set_ylim(bottom=1e-3)  # the first sample starts on the mocap (0)
    axes[1].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    numbers["files"] = {"plot": str(save_figure(fig, out / "contrast.png"))}
    if exp.magnitudes:
        from neuromotor.studies.sweep import SweepSpec, plot_sweep, simulate_grid, table_columns, write_csv

        spec = SweepSpec(list(exp.magnitudes), list(exp.controllers), kind="force" if cfg.perturbations else "ball")
        res = simulate_grid(cfg, spec, base_setup, chunk=len(spec.magnitudes) * len(spec.gains), progress=progress)
        numbers["files"]["sweep_csv"] = str(write_csv(res.rows, out / "sweep.csv", table_columns(cfg, spec)))
        numbers["files"]["sweep_plot"] = str(
            plot_sweep(res.rows, out / "contrast_sweep.png", title="same hit, growing magnitude")
        )
    write_json(numbers, out / "metrics.json")
    return numbers


RUNNERS = {"arm": arm, "full_body": full_body, "contrast": contrast}


def run_experiment(path, kind: str | None = None, output=None, progress: bool = True) -> dict:
    """Run the experiment a config describes (``experiment.kind``, or ``kind`` as default);
    returns the numbers written to ``metrics.json``."""
    cfg, exp = load_experiment(path, kind)
    if kind is not None and exp.kind != kind:
        raise ConfigError(f"{cfg.source}: field 'experiment.kind' is {exp.kind!r}, this script runs {kind!r}")
    if output is not None:
        exp = dataclasses.replace(exp, output=pathlib.Path(output))
    if exp.kind == "contrast":
        return contrast(cfg, exp, progress)
    return RUNNERS[exp.kind](cfg, exp)
