"""Matplotlib summary of a run: the joint-angle deviation over time and the most deflected DOFs."""

from __future__ import annotations

import pathlib

import numpy as np

from neuromotor.atomic import atomic_path
from neuromotor.io.runfile import PLOT_FIELDS, json_field
from neuromotor.viz.data import RenderError, load_run


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _number(m: dict, key):
    """A numeric metric (not a bool), or None."""
    v = m.get(key)
    return v if isinstance(v, (int, float)) and not isinstance(v, bool) else None


def _deviation_title(ax, d) -> str:
    """The title of the deviation panel, quoting the peak and recovery from ``metrics_json``;
    draws the recovery threshold when the metrics give one."""
    title = "Deviation from the unperturbed motion"
    if "metrics_json" not in d:
        return title
    m = json_field(d, "metrics_json") or {}
    bits = []
    if _number(m, "peak_deviation_deg") is not None:
        bits.append(
            f"peak {_number(m, 'peak_deviation_deg'):.2f} deg"
            + (f" at {_number(m, 'time_of_peak_s'):.2f} s" if _number(m, "time_of_peak_s") is not None else "")
        )
    if _number(m, "recovery_time_s") is not None:
        recovery = _number(m, "recovery_time_s")
        bits.append(f"recovered after {recovery:.2f} s" if np.isfinite(recovery) else "not recovered in the window")
    threshold = _number(m, "recovery_threshold_deg")
    if threshold is not None:
        ax.axhline(threshold, color="0.5", ls=":", lw=1, label=f"recovery threshold ({threshold:g} deg)")
    if bits:
        title += " (" + ", ".join(bits) + ")"
    return title


def _plot_deviation(ax, d, t, rms):
    """RMS deviation over time, with the force magnitude on a twin axis."""
    fmag = np.linalg.norm(d["force_vector"], axis=1)
    ax.plot(t, rms, color="tab:orange", lw=2, label="RMS deviation (perturbed - unperturbed)")
    ax.set_xlabel("time (s)")
    metric = str(d["deviation_metric"]) if "deviation_metric" in d else "euler"
    ax.set_ylabel("RMS joint rotation deviation (deg)" if metric == "geodesic" else "RMS joint-angle deviation (deg)")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.fill_between(t, fmag, color="tab:red", alpha=0.18, lw=0)
    ax2.plot(t, fmag, color="tab:red", lw=1, label="force magnitude")
    ax2.set_ylabel("force (N)", color="tab:red")
    ax2.tick_params(axis="y", colors="tab:red")
    ax2.set_ylim(0, max(fmag.max(), 1.0) * 1.15)
    ax.set_title(_deviation_title(ax, d))
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)


def _plot_dof(a, d, t, dev, j, name, legend):
    """One DOF's desired, unperturbed and perturbed angle (deg) over time."""
    ref = np.degrees(d["theta_unperturbed"][:, j])
    # Perturbed as unperturbed plus the wrapped deviation, so curves do not jump at +-180 deg.
    a.plot(t, np.degrees(d["theta_desired"][:, j]), color="0.55", lw=1, ls="--", label="desired (mocap)")
    a.plot(t, ref, color="tab:blue", lw=1.5, label="unperturbed")
    a.plot(t, ref + dev[:, j], color="tab:orange", lw=1.5, label="perturbed")
    a.set_title(f"{name} (max deflection {np.abs(dev[:, j]).max():.1f} deg)", fontsize=9)
    a.set_xlabel("time (s)", fontsize=8)
    a.set_ylabel("angle (deg)", fontsize=8)
    a.tick_params(labelsize=8)
    a.grid(alpha=0.3)
    if legend:
        a.legend(fontsize=7)


def plot_run(run_path, out_png, n_joints: int = 4) -> pathlib.Path:
    """Matplotlib summary of a run: the RMS joint-angle deviation of the perturbed from the
    unperturbed motion (deg) with the force magnitude on a twin axis, and the ``n_joints`` most
    deflected DOFs against their unperturbed and desired (mocap) values."""
    out = pathlib.Path(out_png)
    if out.suffix.lower() != ".png":
        raise RenderError(f"{out}: unknown output extension {out.suffix!r}; plots are written as .png")
    d = load_run(run_path, PLOT_FIELDS)
    from matplotlib.figure import Figure  # no pyplot: no GUI backend is ever touched

    t = d["time"]
    dev = np.degrees(_wrap(d["theta"] - d["theta_unperturbed"]))
    # The curve the metrics came from (geodesic by default); older files: the Euler-DOF RMS.
    rms = np.asarray(d["deviation"]) if "deviation" in d else np.sqrt(np.mean(dev**2, axis=1))
    names = [str(n) for n in d["dof_names"]]
    n_show = min(n_joints, len(names))
    order = np.argsort(-np.abs(dev).max(axis=0))[:n_show]

    fig = Figure(figsize=(10, 3.2 + 2.4 * int(np.ceil(n_show / 2))), dpi=100, layout="constrained")
    rows = 1 + int(np.ceil(n_show / 2))
    gs = fig.add_gridspec(rows, 2, height_ratios=[1.3] + [1] * (rows - 1))
    _plot_deviation(fig.add_subplot(gs[0, :]), d, t, rms)
    for i, j in enumerate(order):
        _plot_dof(fig.add_subplot(gs[1 + i // 2, i % 2]), d, t, dev, j, names[j], i == 0)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    return out
