"""The JSON and CSV files of the studies (fit.json, metrics.json, sweep.csv), each written through
a temporary file renamed into place (:func:`neuromotor.atomic.atomic_path`)."""

from __future__ import annotations

import csv
import json
import math
import pathlib
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from neuromotor.atomic import atomic_path

TEXT_COLUMNS = {
    "label",
    "controller",
    "body",
    "diverged_body",
    "kind",
    "hit_body",
    "dtype",
    "feedback",
    "stability",
    "path",
    "fall_body",
}  # feedback, stability, path: the reflex studies (studies.reflex); fall_body: a sweep on the ground
INT_COLUMNS = {"run", "diverged_step"}


def atomic_write(path, write: Callable, mode: str = "w") -> pathlib.Path:
    """Open a temporary file beside ``path`` (text or ``"wb"``), ``write(fh)``, rename it into place."""
    path = pathlib.Path(path)
    with atomic_path(path) as tmp, open(tmp, mode, newline="" if "b" not in mode else None) as fh:
        write(fh)
    return path


def json_safe(obj):
    """Plain JSON values: NaN and infinities become null, numpy scalars Python numbers."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def write_json(path, data: Any, strict: bool = True) -> pathlib.Path:
    """Indented JSON. ``strict``: standard JSON (a NaN raises; pass :func:`json_safe` data);
    otherwise NaN is written as such and unknown numbers go through ``float``."""

    def write(fh):
        if strict:
            json.dump(data, fh, indent=2, allow_nan=False)
            fh.write("\n")
        else:
            json.dump(data, fh, indent=2, default=float)

    return atomic_write(path, write)


def write_csv(rows: list[dict], path, columns: Sequence[str]) -> pathlib.Path:
    """One row per dict, floats written with ``repr`` (round-trip exact)."""

    def write(fh):
        w = csv.DictWriter(fh, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(float(v)) if isinstance(v, (float, np.floating)) else v) for k, v in r.items()})

    return atomic_write(path, write)


def _cell(key: str, value: str):
    if key in TEXT_COLUMNS:
        return value
    if key in ("diverged", "fell"):
        return value == "True"
    if value == "":  # None: e.g. fall_time_s of a run that did not fall
        return None
    if key in INT_COLUMNS:
        return int(value)
    return float(value)


def read_csv(path) -> list[dict]:
    """Rows of :func:`write_csv`, numbers parsed back."""
    with open(path, newline="", encoding="utf-8") as fh:
        return [{k: _cell(k, v) for k, v in r.items()} for r in csv.DictReader(fh)]
