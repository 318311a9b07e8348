"""Figures of a sweep: recovery against magnitude (sweep.png) and over the (ks, kd) grid
(gains_map.png)."""

from __future__ import annotations

import pathlib

import numpy as np

from neuromotor.viz.figures import pyplot, save_png

save_figure = save_png


def _series_name(r: dict) -> str:
    """The controller of a row: its gain setting's label and, with a reflex, the reflex paths."""
    if "reflex_gain" not in r:
        return r["label"]
    name = f"{r['label']}, reflex {r['reflex_gain']:g}/s$^2$ at {1000 * r['reflex_delay']:g} ms"
    if r.get("long_latency_gain"):
        name += f" + {r['long_latency_gain']:g}/s$^2$ at {1000 * r['long_latency_delay']:g} ms"
    return name


def _series_key(r: dict) -> tuple:
    if r.get("kind") == "ball":  # an aimed ball's direction changes with its speed: one series
        return (_series_name(r), r["body"], 0.0, 0.0, 0.0, r["start"])
    return (_series_name(r), r["body"], r["direction_x"], r["direction_y"], r["direction_z"], r["start"])


# The x axis of a sweep, in the units of the swept magnitude (sweep.csv's kind column).
MAGNITUDE_LABELS = {"force": "pulse magnitude (N)", "impulse": "impulse (N s)", "ball": "ball speed (m/s)"}


def plot_sweep(rows: list[dict], path, title: str = "", xlabel: str | None = None) -> pathlib.Path:
    """Peak deviation and recovery time against magnitude, one line per gain setting (and per
    body / direction / start when those vary too). Diverged runs: red crosses on the axis.
    ``xlabel`` defaults to the pulse magnitude, or the ball speed for ball rows."""
    plt = pyplot()
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(_series_key(r), []).append(r)
    varying = [len({k[i] for k in groups}) > 1 for i in range(6)]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=90)
    for key, rs in groups.items():
        rs = sorted(rs, key=lambda r: r["magnitude"])
        parts = [key[0]] if varying[0] or not any(varying) else []
        if varying[1]:
            parts.append(key[1])
        if any(varying[2:5]):
            parts.append(f"dir ({key[2]:.2g}, {key[3]:.2g}, {key[4]:.2g})")
        if varying[5]:
            parts.append(f"t={key[5]:g}s")
        label = ", ".join(parts)
        m = np.array([r["magnitude"] for r in rs])
        bad = np.array([r["diverged"] for r in rs])
        for ax, col in zip(axes, ("peak_deviation_deg", "recovery_time_s")):
            y = np.array([r[col] for r in rs], float)
            (line,) = ax.plot(m[~bad], y[~bad], "o-", ms=3, label=label)
            # Runs still outside the recovery band at the window's end: open triangles on top.
            late = ~bad & ~np.isfinite(y)
            if late.any():
                ax.plot(
                    m[late],
                    np.ones(late.sum()),
                    "^",
                    mfc="none",
                    color=line.get_color(),
                    ms=7,
                    clip_on=False,
                    transform=ax.get_xaxis_transform(),
                )
            if bad.any():
                ax.plot(
                    m[bad],
                    np.zeros(bad.sum()),
                    "x",
                    color="red",
                    ms=7,
                    clip_on=False,
                    transform=ax.get_xaxis_transform(),
                    label="diverged" if ax is axes[0] else None,
                )
    if xlabel is None:
        xlabel = MAGNITUDE_LABELS.get(
            rows[0].get("kind") if rows else None,  # type: ignore[arg-type]  # None: default
            MAGNITUDE_LABELS["force"],
        )
    axes[0].set(xlabel=xlabel, ylabel="peak deviation (deg)")
    axes[1].set(xlabel=xlabel, ylabel="recovery time (s)")
    axes[1].set_title("open triangle: not recovered by the window's end; red x: diverged", fontsize=7)
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_gains_map(rows: list[dict], path, fitted: tuple[float, float] | None = None, title: str = "") -> pathlib.Path:
    """Heat maps of recovery time and peak deviation over the (ks, kd) grid of one hit.

    Cells whose run diverged (or never recovered) are grey with a cross; the fitted pair is a
    white star."""
    plt = pyplot()
    ks = np.array(sorted({r["ks"] for r in rows}))
    kd = np.array(sorted({r["kd"] for r in rows}))
    grid = {(r["ks"], r["kd"]): r for r in rows}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=90)

    def edges(v):
        if len(v) == 1:
            return np.array([v[0] * 0.8, v[0] * 1.25])
        lv = np.log(v)
        mid = 0.5 * (lv[1:] + lv[:-1])
        return np.exp(np.concatenate([[2 * lv[0] - mid[0]], mid, [2 * lv[-1] - mid[-1]]]))

    for ax, col, name in zip(
        axes, ("recovery_time_s", "peak_deviation_deg"), ("recovery time (s)", "peak deviation (deg)")
    ):
        z = np.full((len(kd), len(ks)), np.nan)
        bad = np.zeros_like(z, bool)
        late = np.zeros_like(z, bool)
        for i, b in enumerate(kd):
            for j, a in enumerate(ks):
                r = grid.get((a, b))
                if r is not None:
                    z[i, j] = r[col]
                    bad[i, j] = bool(r["diverged"])
                    late[i, j] = not bad[i, j] and not np.isfinite(r[col])
        cmap = plt.get_cmap("viridis").with_extremes(bad="0.7")
        mesh = ax.pcolormesh(edges(ks), edges(kd), np.ma.masked_invalid(z), cmap=cmap, shading="flat")
        fig.colorbar(mesh, ax=ax, label=name)
        yy, xx = np.nonzero(bad)
        if len(xx):
            ax.plot(ks[xx], kd[yy], "x", color="red", ms=6, label="diverged")
        yy, xx = np.nonzero(late)
        if len(xx):
            ax.plot(ks[xx], kd[yy], "o", mfc="none", color="black", ms=5, label="not recovered in the window")
        if fitted is not None:
            ax.plot([fitted[0]], [fitted[1]], "*", color="white", mec="black", ms=16, label="fitted (ks, kd)")
        ax.set(xscale="log", yscale="log", xlabel="ks (1/s$^2$)", ylabel="kd (1/s)", title=name)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc="upper left")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)
