"""The figure of a calibration (fit.png): the target, the fitted response and the response at the
starting gains, one row per perturbation case."""

from __future__ import annotations

import pathlib

import numpy as np

from neuromotor.viz.figures import pyplot, save_png


def _band(ax, row: dict, name: str, label: str) -> None:
    if name in row:
        v, sd = row[name]["value"], row[name]["sd"]
        ax.axhspan(v - sd, v + sd, color="k", alpha=0.12, label=label)


def _feature_panel(ax, cal, c: int, col: int, unit: str) -> None:
    """Deviation (col 0) or acceleration (col 1) of a feature fit, with the target values marked."""
    row = cal.feature_table[c]
    if col == 1:
        _band(ax, row, "peak_acceleration_deg_s2", "target peak ± sd")
        ax.set_ylabel("acceleration (deg/s²)")
        ax.set_title(f"case {c}: angular acceleration of the deviation", fontsize=9)
        return
    start = float(cal.problem.start[c])
    _band(ax, row, "peak_deviation_deg", "target peak ± sd")
    if "time_to_peak_s" in row:
        ax.axvline(start + row["time_to_peak_s"]["value"], color="k", ls=":", label="target time to peak")
    if "recovery_time_s" in row:
        ax.axvline(start + row["recovery_time_s"]["value"], color="k", ls="-.", lw=0.8, label="target recovery")
    ax.set_ylabel(f"deviation ({unit})")
    ax.set_title(f"case {c}", fontsize=9)


def _columns(cal, ev_start, ev_fit, max_columns: int) -> list[int]:
    if cal.problem.spec.kind == "features":  # deviation, and the acceleration when it is fitted
        return [0, 1] if "peak_acceleration_deg_s2" in cal.problem.spec.features else [0]
    # Show the columns the gains move most (start vs fitted), not those the mocap moves most.
    spread = np.abs(ev_start.curves - ev_fit.curves).max(axis=(0, 1))
    return list(np.argsort(-spread)[:max_columns])


def _title(res) -> str:
    return (
        f"{res.solver}: ks = {res.ks:.4g} ± {res.se_ks:.2g} 1/s², kd = {res.kd:.4g} ± {res.se_kd:.2g} 1/s\n"
        f"(start ks = {res.ks0:.4g}, kd = {res.kd0:.4g}; {res.status}, {res.iterations} iterations)"
    )


def plot_fit(cal, ev_start, ev_fit, path, res=None, max_columns: int = 4) -> pathlib.Path:
    """PNG: the target, the fitted response and the response at the starting gains of a
    :class:`~neuromotor.studies.fit.Calibration` (evaluations at the start and fitted gains)."""
    plt = pyplot()
    t, kind, n_cases = cal.time, cal.problem.spec.kind, cal.problem.n_cases
    feats = kind == "features"
    cols = _columns(cal, ev_start, ev_fit, max_columns)
    tgt = None if feats else cal.target_curves()
    fig, axes = plt.subplots(
        n_cases, len(cols), figsize=(max(3.6 * len(cols), 7.0), 2.7 * n_cases + 0.6), squeeze=False
    )
    scale = 1.0 if feats or kind == "body_positions" else 180.0 / np.pi
    unit = "deg" if feats or kind == "joint_angles" else "m"
    for c in range(n_cases):
        for j, col in enumerate(cols):
            ax = axes[c, j]
            if tgt is not None:  # trajectory targets
                ax.plot(t, scale * tgt[c, :, col], "k.", ms=3, label="target")
            ax.plot(t, scale * ev_fit.curves[c, :, col], "C0-", lw=1.6, label="fitted")
            ax.plot(t, scale * ev_start.curves[c, :, col], "C3--", lw=1.2, label="start")
            if feats:
                _feature_panel(ax, cal, c, col, unit)
            else:
                ax.set_title(f"case {c}: {cal.labels[col]}", fontsize=9)
                ax.set_ylabel(unit)
            ax.set_xlabel("clip time (s)")
            if c == 0 and (j == 0 or feats):
                ax.legend(fontsize=7)
    if res is not None:
        fig.suptitle(_title(res), fontsize=9)
    fig.tight_layout()
    return save_png(fig, pathlib.Path(path), dpi=110)
