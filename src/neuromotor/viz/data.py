"""The arrays of a RUN.npz that drawing needs, read and checked by :mod:`neuromotor.io.runfile`;
every problem with the input or the output of a picture is a :class:`RenderError`."""

from __future__ import annotations

from neuromotor.errors import UserError
from neuromotor.io.runfile import DRAW_FIELDS, read_run


class RenderError(UserError):
    """Bad input or output for rendering; the message names the file and the field."""


def load_run(run_path, fields=DRAW_FIELDS):
    """Read and check the arrays of a RUN.npz needed for drawing (``fields``) plus the optional
    ``up_axis``, ``ball_pos``, ``ball_radius``, ``metrics_json``, ``facing``,
    ``skeleton_edge_body`` and (when drawing, all or none) the body shapes and poses
    ``shape_vertices``, ``shape_faces``, ``shape_body``, ``body_pos``, ``body_quat`` and their
    ``_unperturbed`` twins."""
    return read_run(run_path, fields, error=RenderError)
