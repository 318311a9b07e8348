"""The figure of a calibration (fit.png): the target (a corridor as its mean +- sd band), the
fitted response and the response at the starting gains, one row per perturbation case and a
panel per target (per curve the gains move most, for targets of several DOFs or bodies)."""

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
    # Show the columns the gains move most (start vs fitted), not those the mocap moves most:
    # every target gets its own panels.
    spread = np.abs(ev_start.curves - ev_fit.curves).max(axis=(0, 1))
    cols: list[int] = []
    blocks = cal.report_blocks()
    share = max(1, max_columns // len(blocks))
    for b in blocks:
        c0, c1 = b["columns"]
        cols += [c0 + int(k) for k in np.argsort(-spread[c0:c1])[:share]]
    return cols


def _block_of(cal, col: int) -> dict:
    return next(b for b in cal.report_blocks() if b["columns"][0] <= col < b["columns"][1])


def _title(res, units=None) -> str:
    """Every fitted parameter with its standard error and unit (``units``: name -> unit), and
    where the fit started."""
    units = units or {"ks": "1/s²", "kd": "1/s"}
    names = list(res.values) or ["ks", "kd"]
    values = res.values or {"ks": res.ks, "kd": res.kd}
    start = res.start_values or {"ks": res.ks0, "kd": res.kd0}
    se = res.standard_errors or {"ks": res.se_ks, "kd": res.se_kd}
    fitted = ", ".join(f"{n} = {values[n]:.4g} ± {se[n]:.2g} {units.get(n, '')}".rstrip() for n in names)
    began = ", ".join(f"{n} = {start[n]:.4g}" for n in names)
    return f"{res.solver}: {fitted}\n(start {began}; {res.status}, {res.iterations} iterations)"


def plot_fit(cal, ev_start, ev_fit, path, res=None, max_columns: int = 4, units=None) -> pathlib.Path:
    """PNG: the target, the fitted response and the response at the starting gains of a
    :class:`~neuromotor.studies.fit.Calibration` (evaluations at the start and fitted gains)."""
    plt = pyplot()
    t, kind, n_cases = cal.time, cal.problem.spec.kind, cal.problem.n_cases
    feats = kind == "features"
    cols = _columns(cal, ev_start, ev_fit, max_columns)
    tgt = None if feats else cal.target_curves()
    fig, axes = plt.subplots(
        n_cases, len(cols), figsize=(max(4.2 * len(cols), 7.0), 2.7 * n_cases + 0.6), squeeze=False
    )
    sd = None if feats or cal.sd is None else cal.sd.reshape(tgt.shape)  # type: ignore[union-attr]
    for c in range(n_cases):
        start = float(cal.problem.start[c])
        for j, col in enumerate(cols):
            ax = axes[c, j]
            if feats:
                scale, unit = 1.0, "deg"
            else:
                block = _block_of(cal, col)
                scale, unit = block["scale"], block["unit"]
                mean = scale * tgt[c, :, col]  # type: ignore[index]
                band = None if sd is None or not np.all(np.isfinite(sd[c, :, col])) else scale * sd[c, :, col]
                if band is not None:  # a corridor: mean +- sd over subjects
                    ax.fill_between(t, mean - band, mean + band, color="k", alpha=0.15, lw=0, label="target ± sd")
                    ax.plot(t, mean, "k-", lw=0.8)
                else:
                    ax.plot(t, mean, "k.", ms=3, label="target")
            ax.plot(t, scale * ev_fit.curves[c, :, col], "C0-", lw=1.6, label="fitted")
            ax.plot(t, scale * ev_start.curves[c, :, col], "C3--", lw=1.2, label="start")
            if feats:
                _feature_panel(ax, cal, c, col, unit)
            else:
                if t[0] <= start <= t[-1]:
                    ax.axvline(start, color="0.6", lw=0.8, ls=":")
                ax.set_title(f"case {c}: {cal.labels[col]}", fontsize=9)
                ax.set_ylabel(unit)
            ax.set_xlabel("clip time (s)")
            if c == 0 and (j == 0 or feats):
                ax.legend(fontsize=7)
    if res is not None:
        fig.suptitle(_title(res, units), fontsize=9)
    fig.tight_layout()
    return save_png(fig, pathlib.Path(path), dpi=110)
