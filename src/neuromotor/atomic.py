"""Atomic output files: write to a temporary file beside the target, rename on success.

A reader never sees a half-written file, and a failure (bad input found late, a full disk, an
interrupt) leaves no partial output behind:

* the temporary is ``.NAME.neuromotor-PID-XXXXXXXX.tmp.EXT`` in the target's folder (hidden,
  the writing process's id in the name, the target's extension last so that writers which pick
  the format from the name still do);
* it is renamed over the target only when the block succeeds, and removed when it raises;
* while a temporary exists, SIGINT, SIGTERM and SIGHUP remove it before the process goes on
  to what the signal would have done anyway (``KeyboardInterrupt``, or dying of the signal); a
  signal the process ignores (as a background job ignores SIGINT) is left ignored;
* a process killed with SIGKILL cannot clean up: the next atomic write into the same folder
  removes this program's temporaries whose process is gone or that have not been touched for
  :data:`STALE_AFTER_S` seconds.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import re
import signal
import stat
import tempfile
import threading
import time
from collections.abc import Iterator
from typing import Any

TAG = "neuromotor"
# .NAME.neuromotor-PID-RANDOM.tmp[.EXT]; RANDOM is tempfile's [a-z0-9_]{8}.
_TEMP_RE = re.compile(r"\..*\." + TAG + r"-(\d+)-[A-Za-z0-9_]+\.tmp(\.[^/]*)?", re.DOTALL)
STALE_AFTER_S = 3600.0

_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))
_live: set[str] = set()  # absolute paths of this process's temporaries
_lock = threading.RLock()
_previous: dict[int, Any] = {}  # signal number: the handler it had (signal.getsignal)
_depth = 0  # nesting of atomic writes in the main thread (handlers installed while > 0)


def is_temporary(name: str) -> bool:
    """Whether a file name is one of this program's temporaries."""
    return _TEMP_RE.fullmatch(name) is not None


def temporary_prefix_suffix(out: pathlib.Path) -> tuple[str, str]:
    return f".{out.name[:100]}.{TAG}-{os.getpid()}-", ".tmp" + out.suffix[:20]  # within NAME_MAX


def remove_live_temporaries() -> None:
    """Remove every temporary this process has open (from a signal handler or at exit)."""
    with _lock:
        paths = list(_live)
        _live.clear()
    for p in paths:
        try:
            os.unlink(p)
        except OSError:
            pass


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # somebody else's process: alive
        return True
    except OSError:
        return False
    return True


def remove_stale_temporaries(directory, max_age_s: float = STALE_AFTER_S) -> list[pathlib.Path]:
    """Remove this program's temporaries in ``directory`` left by a process that is gone (killed
    with SIGKILL, a power cut) or untouched for ``max_age_s`` seconds; return what was removed.
    Other processes' live temporaries and anything not named like ours are left alone. (The PID
    test is local to this machine: on a folder shared between hosts, only the age counts for a
    PID that happens to be alive here.)"""
    removed: list[pathlib.Path] = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        m = _TEMP_RE.fullmatch(entry.name)
        if m is None:
            continue
        path = os.path.abspath(entry.path)
        with _lock:
            if path in _live:
                continue
        try:
            st = entry.stat(follow_symlinks=False)
        except OSError:
            continue
        if not stat.S_ISREG(st.st_mode):
            continue
        pid = int(m.group(1))
        mine_but_not_live = pid == os.getpid()  # a dead process's, whose PID we now have
        if mine_but_not_live or not _pid_alive(pid) or now - st.st_mtime > max_age_s:
            try:
                os.unlink(path)
                removed.append(pathlib.Path(path))
            except OSError:
                pass
    return removed


def _on_signal(signum, frame):
    remove_live_temporaries()
    previous = _previous.get(signum, signal.SIG_DFL)
    if callable(previous):  # e.g. Python's SIGINT handler: KeyboardInterrupt
        previous(signum, frame)
        return
    # The default action (terminate): die of the same signal, so the exit status says so.
    signal.signal(signum, signal.SIG_DFL)
    os.kill(os.getpid(), signum)


def _install_handlers() -> bool:
    global _depth
    if threading.current_thread() is not threading.main_thread():
        return False
    with _lock:
        if _depth == 0:
            for s in _SIGNALS:
                try:
                    prev = signal.getsignal(s)
                    # An ignored signal stays ignored (a background job's SIGINT, nohup's SIGHUP):
                    # a handler would remove the temporary of a write that then goes on.
                    if prev == signal.SIG_IGN:
                        continue
                    signal.signal(s, _on_signal)
                except (OSError, ValueError):
                    continue
                _previous[s] = signal.SIG_DFL if prev is None else prev
        _depth += 1
    return True


def _restore_handlers() -> None:
    global _depth
    with _lock:
        _depth -= 1
        if _depth == 0:
            for s, prev in list(_previous.items()):
                try:
                    if signal.getsignal(s) is _on_signal:
                        signal.signal(s, prev)
                except (OSError, ValueError):
                    pass
            _previous.clear()


def _renamed(e: OSError, tmp: str, out: pathlib.Path) -> OSError:
    """``e`` naming the target instead of the hidden temporary."""
    if e.filename is not None and os.path.abspath(os.fspath(e.filename)) == tmp:
        new = type(e)(e.errno, e.strerror, str(out)) if e.errno is not None else type(e)(f"{out}: {e}")
        return new
    return e


def _file_mode(out: pathlib.Path) -> int:
    try:
        st = os.stat(out)
        if stat.S_ISREG(st.st_mode):
            return stat.S_IMODE(st.st_mode)  # replacing a file keeps its permissions
    except OSError:
        pass
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask  # mkstemp makes 0600; give the usual permissions


def _fsync(path, directory=False) -> None:
    try:
        fd = os.open(path, os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def _signals_blocked(active: bool) -> Iterator[None]:
    if not (active and hasattr(signal, "pthread_sigmask")):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextlib.contextmanager
def atomic_path(out_path, make_parents: bool = True) -> Iterator[pathlib.Path]:
    """Yield a temporary path beside ``out_path`` (same suffix); rename it onto ``out_path``
    when the block succeeds, delete it when it raises or the process is interrupted. Missing
    parent folders are created (unless ``make_parents`` is false: then a missing folder is an
    ``OSError``). Errors name ``out_path``, never the temporary."""
    out = pathlib.Path(out_path)
    if make_parents:
        out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out.parent)
    prefix, suffix = temporary_prefix_suffix(out)
    installed = _install_handlers()
    try:
        # Created and registered with the signals held back: one in between cannot orphan it.
        with _signals_blocked(installed), _lock:
            try:
                fd, name = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=out.parent)
            except OSError as e:
                raise type(e)(e.errno, e.strerror, str(out)) from None
            tmp = os.path.abspath(name)
            _live.add(tmp)
        os.close(fd)
        try:
            try:
                yield pathlib.Path(name)
            except OSError as e:
                new = _renamed(e, tmp, out)
                if new is e:
                    raise
                raise new from e
            try:
                os.chmod(tmp, _file_mode(out))
                _fsync(tmp)
                os.replace(tmp, out)
            except OSError as e:
                raise _renamed(e, tmp, out) from None
            _fsync(out.parent, directory=True)
        finally:
            with _lock:
                _live.discard(tmp)
            try:
                os.unlink(tmp)
            except OSError:
                pass
    finally:
        if installed:
            _restore_handlers()
