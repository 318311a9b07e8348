"""Pre-flight checks of a command's outputs, before any computation starts.

    check_outputs(files=["run.npz"], folders=[], inputs=["walk.bvh", "hit.toml"])

raises :class:`OutputError` (a ``ValueError``), whose message is one line naming the path, when
an output

* is the same file as one of the inputs (``simulate X.toml -o X.toml``) or is named twice;
* is an existing directory where a file is written, or not a regular file (``/dev/null``: a
  rename would replace the device node);
* is a folder output that exists as something other than a folder;
* lies under a regular file (``-o notes.txt/run.npz``);
* cannot be written: a probe file is created and removed in the target's folder (or, when that
  folder does not exist yet, in its nearest existing ancestor, where it would be created), so a
  read-only file system, a missing permission or a full inode table shows now rather than after
  minutes of simulation.

Missing parent folders are not an error: the writers create them (``-o out/new/run.npz``).
"""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Iterable

from neuromotor.atomic import TAG
from neuromotor.errors import UserError


class OutputError(UserError):
    """An output that must not or cannot be written; the message names it."""


def _fspath(p) -> str:
    return os.fspath(p)


def _nearest_existing(path: str) -> str:
    """``path`` or its nearest ancestor that exists (as anything)."""
    a = os.path.abspath(path)
    while not os.path.lexists(a):
        parent = os.path.dirname(a)
        if parent == a:
            break
        a = parent
    return a


def _probe(directory: str, shown: str, cache: dict[str, None]) -> None:
    if directory in cache:
        return
    try:
        fd, name = tempfile.mkstemp(prefix=f".probe.{TAG}-{os.getpid()}-", suffix=".tmp", dir=directory)
    except OSError as e:
        where = "" if os.path.abspath(shown) == directory else f" (in {directory})"
        raise OutputError(f"{shown}: cannot write{where}: {e.strerror or e}") from None
    os.close(fd)
    try:
        os.unlink(name)
    except OSError:
        pass
    cache[directory] = None


def _check_parent(shown: str, path: str, probes: dict) -> None:
    """The folder that will hold ``path`` is a folder (or can be created) and is writable."""
    parent = os.path.dirname(os.path.abspath(path))
    base = _nearest_existing(parent)
    if not os.path.isdir(base):
        raise OutputError(f"{shown}: {base} is not a directory")
    _probe(base, shown, probes)


def _same(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_outputs(files: Iterable = (), folders: Iterable = (), inputs: Iterable = ()) -> None:
    """Refuse outputs that would destroy an input or cannot be written (module docstring).
    ``None`` entries are skipped; inputs that do not exist are the reader's business."""
    files = [_fspath(f) for f in files if f is not None]
    folders = [_fspath(d) for d in folders if d is not None]
    inputs = [_fspath(i) for i in inputs if i is not None and os.path.exists(_fspath(i))]
    probes: dict[str, None] = {}
    for d in folders:
        if d == "":
            raise OutputError("the output folder is an empty path")
        if os.path.lexists(d) and not os.path.isdir(d):
            raise OutputError(f"{d}: exists and is not a directory (an output folder is needed)")
        for i in inputs:
            if os.path.exists(d) and _same(d, i):
                raise OutputError(f"{d}: is the input {i}; refusing to write over it")
        if os.path.isdir(d):
            _probe(os.path.abspath(d), d, probes)
        else:
            _check_parent(d, d, probes)
    seen: dict[str, str] = {}
    for f in files:
        if f == "":
            raise OutputError("the output file is an empty path")
        if os.path.isdir(f):
            raise OutputError(f"{f}: is a directory; give a file name")
        if os.path.lexists(f) and os.path.exists(f) and not stat.S_ISREG(os.stat(f).st_mode):
            raise OutputError(
                f"{f}: is not a regular file (a device, pipe or socket); outputs are replaced, so give a file name"
            )
        for i in inputs:
            if os.path.exists(f) and _same(f, i):
                same = "" if os.path.abspath(f) == os.path.abspath(i) else f" {i}"
                raise OutputError(
                    f"{f}: is also the input{same} of this command; refusing to overwrite it (give another output name)"
                )
        key = os.path.realpath(f)
        if key in seen:
            raise OutputError(f"{f}: is named twice as an output ({seen[key]})")
        seen[key] = f
        _check_parent(f, f, probes)


def inputs_of_run(run_path) -> list[str]:
    """The clip a RUN.npz was made from (``source_clip``), when it can be read cheaply."""
    from neuromotor.io.runfile import source_clip

    clip = source_clip(run_path)
    return [] if clip is None else [clip]
