"""Atomic output files: write to a temporary file beside the target, rename on success.

A reader never sees a half-written file, and a failure (bad input found late, a full disk, an
interrupt) leaves no partial output behind.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import tempfile
from collections.abc import Iterator


@contextlib.contextmanager
def atomic_path(out_path) -> Iterator[pathlib.Path]:
    """Yield a temporary path beside ``out_path`` (same suffix); rename it onto ``out_path``
    when the block succeeds, delete it when it raises."""
    out = pathlib.Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out.stem}-", suffix=out.suffix, dir=out.parent)
    os.close(fd)
    tmp = pathlib.Path(tmp)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
