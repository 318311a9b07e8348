"""Matplotlib without a display, and PNG files written atomically."""

from __future__ import annotations

import pathlib


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path, dpi=None) -> pathlib.Path:
    """Save a matplotlib figure as PNG through a temporary file, and close it."""
    from neuromotor.io.tables import atomic_write

    try:
        return atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=dpi or fig.dpi), "wb")
    finally:
        pyplot().close(fig)
