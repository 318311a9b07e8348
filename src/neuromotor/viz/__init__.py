"""Pictures of a run: filmstrip, video and plots (see :mod:`neuromotor.viz.render`), and the
interactive viewer (:mod:`neuromotor.viz.html`).

The names below are imported on first use, like the package's own (``import neuromotor.viz``
stays quick)."""

import importlib

# public name -> module that defines it
_API = {
    "render_run": "neuromotor.viz.render",
    "plot_run": "neuromotor.viz.render",
    "show": "neuromotor.viz.html",
    "write_viewer": "neuromotor.viz.html",
    "viewer_html": "neuromotor.viz.html",
}

__all__ = list(_API)


def __getattr__(name: str):
    if name in _API:  # imported on first use
        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted([*globals(), *_API])
