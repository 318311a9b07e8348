"""Figures of the delayed reflex (:mod:`neuromotor.studies.reflex`): the deviation curves of one
hit under the feedback paths, and the stability map over reflex gain x loop delay."""

from __future__ import annotations

import pathlib

import numpy as np

from neuromotor.viz.figures import pyplot, save_png

STATUS_MARKERS = {
    "diverged": ("x", "red", "diverged"),
    "large": ("^", "darkorange", "peak beyond the bound"),
    "sustained": ("s", "purple", "not decaying (end >= half the peak)"),
}


def plot_deviation_paths(
    time, curves: dict[str, np.ndarray], path, hit_start: float, title: str = "", table: dict[str, dict] | None = None
) -> pathlib.Path:
    """d(t) of each run against its own unperturbed twin, one line per feedback configuration;
    ``table`` (name -> recovery metrics) marks each curve's peak and recovery time."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 3.8), dpi=100)
    for name, d in curves.items():
        (line,) = ax.plot(time, d, lw=1.6, label=name)
        m = (table or {}).get(name)
        if m is None:
            continue
        ax.plot([m["time_of_peak_s"]], [m["peak_deviation_deg"]], "o", color=line.get_color(), ms=5)
        if np.isfinite(m["recovery_time_s"]):
            ax.axvline(hit_start + m["recovery_time_s"], color=line.get_color(), ls=":", lw=1)
    ax.axvline(hit_start, color="0.5", lw=0.8)
    ax.set(
        xlabel="clip time (s)",
        ylabel="deviation d(t) (deg)",
        xlim=(max(float(time[0]), hit_start - 0.2), float(time[-1])),
    )
    ax.set_title("dot: peak; dotted: recovered (within max(20 % of peak, 0.5 deg) from then on)", fontsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def _grid(rows: list[dict], key: str) -> tuple[np.ndarray, np.ndarray, dict]:
    gains = np.array(sorted({r["reflex_gain"] for r in rows}))
    delays = np.array(sorted({r["reflex_delay"] for r in rows}))
    cells = {(gains.searchsorted(r["reflex_gain"]), delays.searchsorted(r["reflex_delay"])): r for r in rows}
    return gains, delays, {k: v[key] for k, v in cells.items()}


def _gain_position(gains: np.ndarray, g: float) -> float | None:
    """Column coordinate of gain ``g``: exact on a column, log-interpolated between positive
    ones; None outside the grid."""
    if g in gains:
        return float(np.flatnonzero(gains == g)[0])
    pos = np.flatnonzero(gains > 0)
    if g <= 0 or not len(pos) or not gains[pos[0]] <= g <= gains[-1]:
        return None
    return float(np.interp(np.log(g), np.log(gains[pos]), pos))


def _boundary(ax, stable: np.ndarray, y0: int) -> None:
    """The edges between stable and unstable cells (rows: delays from ``y0`` up, columns: gains)."""
    ny, nx = stable.shape
    for i in range(ny):
        for j in range(nx):
            if j + 1 < nx and stable[i, j] != stable[i, j + 1]:
                ax.plot([j + 0.5, j + 0.5], [y0 + i - 0.5, y0 + i + 0.5], color="black", lw=2.5)
            if i + 1 < ny and stable[i, j] != stable[i + 1, j]:
                ax.plot([j - 0.5, j + 0.5], [y0 + i + 0.5, y0 + i + 0.5], color="black", lw=2.5)


def _layers(rows: list[dict], implicit: list[dict] | None, col: str):
    """Per map row (the implicit reference first, then the delays) and gain column: ``col``,
    the stability, and the y tick labels."""
    gains, delays, _ = _grid(rows, col)
    layers = [[r for r in rows if r["reflex_delay"] == d] for d in delays]
    labels = [f"{1000 * d:g}" for d in delays]
    if implicit:
        layers, labels = [implicit, *layers], ["0, in K, D\n(implicit)", *labels]
    value = np.full((len(layers), len(gains)), np.nan)
    status = np.full(value.shape, "", dtype=object)
    for i, layer in enumerate(layers):
        for r in layer:
            j = int(gains.searchsorted(r["reflex_gain"]))
            value[i, j], status[i, j] = r[col], r["stability"]
    return gains, value, status, labels


def plot_stability_map(
    rows: list[dict],
    path,
    *,
    criterion: str = "",
    paper: tuple[float, float] | None = None,
    paper_label: str = "the paper's controller",
    implicit: list[dict] | None = None,
    title: str = "",
) -> pathlib.Path:
    """Recovery time and peak deviation over the delayed path's gain (columns) x delay (rows),
    for rows classified by :func:`neuromotor.studies.reflex.classify` (key ``stability``);
    ``implicit`` (optional) is a bottom row: the same gains added without delay inside K and D.
    Unstable cells are blank with a marker, stable ones not recovered by the window's end get an
    open circle; the thick line separates stable from unstable delayed cells; the star is
    ``paper`` = (gain, delay), on the implicit row when there is one, labelled ``paper_label``;
    ``criterion`` says what stable means."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.8), dpi=100)
    y0 = 1 if implicit else 0
    for ax, (col, name) in zip(
        axes, (("recovery_time_s", "recovery time (s)"), ("peak_deviation_deg", "peak deviation (deg)"))
    ):
        gains, z, status, labels = _layers(rows, implicit, col)
        stable = status == "stable"
        rec = _layers(rows, implicit, "recovery_time_s")[1]
        mesh = ax.pcolormesh(
            np.arange(len(gains) + 1) - 0.5,
            np.arange(len(labels) + 1) - 0.5,
            np.ma.masked_invalid(np.where(stable, z, np.nan)),
            cmap=plt.get_cmap("viridis").with_extremes(bad="0.85"),
            shading="flat",
        )
        fig.colorbar(mesh, ax=ax, label=name + ", stable cells")
        for s, (marker, colour, label) in STATUS_MARKERS.items():
            yy, xx = np.nonzero(status == s)
            if len(xx):
                ax.plot(xx, yy, marker, color=colour, ms=7, ls="none", label=label)
        yy, xx = np.nonzero(stable & ~np.isfinite(rec))
        if len(xx):
            ax.plot(xx, yy, "o", mfc="none", color="black", ms=6, ls="none", label="not recovered in the window")
        _boundary(ax, stable[y0:], y0)
        if y0:
            ax.axhline(0.5, color="white", lw=3)
        x = None if paper is None else _gain_position(gains, paper[0])
        if x is not None and paper is not None:
            delays = np.array(sorted({r["reflex_delay"] for r in rows}))
            y = 0.0 if y0 else float(np.interp(paper[1], delays, np.arange(len(delays))))
            ax.plot([x], [y], "*", color="white", mec="black", ms=17, clip_on=False, label=paper_label)
        ax.set_xticks(range(len(gains)), [f"{g:g}" for g in gains], fontsize=7)
        ax.set_yticks(range(len(labels)), labels, fontsize=7)
        ax.set(xlabel="added feedback gain g (1/s$^2$)", ylabel="loop delay (ms)", title=name)
    fig.legend(
        *axes[0].get_legend_handles_labels(),
        loc="lower center",
        ncol=4,
        fontsize=8,
        frameon=False,
        bbox_to_anchor=(0.5, 0.04),
    )
    fig.text(
        0.5,
        0.005,
        f"stable: {criterion}; the thick line is the stability boundary of the delayed path",
        ha="center",
        fontsize=8,
    )
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout(rect=(0, 0.1, 1, 1))
    return save_png(fig, path)
