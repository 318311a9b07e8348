"""Reading a TOML table field by field, each error naming the file and the field."""

from __future__ import annotations

import math
import pathlib
import tomllib
from typing import NoReturn

import numpy as np

from neuromotor.errors import ConfigError


def read_toml(path) -> dict:
    """The TOML table of a config file; an unreadable, binary, empty or comment-only file is a
    :class:`ConfigError` naming the file (an empty config would silently run the defaults)."""
    path = pathlib.Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise ConfigError(f"{path}: cannot read config: {e.strerror}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"{path}: not a text (UTF-8 TOML) config: byte 0x{raw[e.start]:02x} at offset {e.start}"
        ) from None
    if "\x00" in text:
        raise ConfigError(f"{path}: not a text (TOML) config: NUL byte at offset {text.index(chr(0))}")
    if not text.strip():
        raise ConfigError(f"{path}: config is empty")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML: {e}") from None
    if not data:
        raise ConfigError(f"{path}: config has no settings (only comments)")
    return data


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


class Fields:
    """Typed getters over one table that name the field on error and reject unknown keys."""

    used: set[str]  # the keys read so far

    def __init__(self, table, where: str, source: str):
        if not isinstance(table, dict):
            raise ConfigError(f"{source}: {where} must be a table")
        self.table, self.where, self.source, self.used = table, where, source, set()

    def name(self, key) -> str:
        return f"{self.where}.{key}" if self.where else key

    def fail(self, key, msg) -> NoReturn:
        raise ConfigError(f"{self.source}: field '{self.name(key)}' {msg}")

    def sub(self, key, default=None) -> Fields:
        """The sub-table ``key`` as its own reader."""
        return Fields(self.get(key, {} if default is None else default), self.name(key), self.source)

    def get(self, key, default=None):
        self.used.add(key)
        return self.table.get(key, default)

    def number(self, key, default, *, positive=False, nonneg=False):
        val = self.get(key, default)
        if val is None:
            return None
        if not _is_number(val) or not math.isfinite(val):
            self.fail(key, f"must be a finite number, got {val!r}")
        if positive and not val > 0:
            self.fail(key, f"must be > 0, got {val!r}")
        if nonneg and val < 0:
            self.fail(key, f"must be >= 0, got {val!r}")
        return float(val)

    def required(self, key, value, msg: str = "is required"):
        if value is None:
            self.fail(key, msg)
        return value

    def integer(self, key, default, low: int, msg: str | None = None) -> int:
        val = self.get(key, default)
        if isinstance(val, bool) or not isinstance(val, int) or val < low:
            self.fail(key, (msg or f"must be an integer >= {low}") + f", got {val!r}")
        return int(val)

    def vector(self, key, default):
        val = self.get(key, default)
        if not isinstance(val, list) or len(val) != 3 or not all(_is_number(x) for x in val):
            self.fail(key, f"must be a list of 3 numbers, got {val!r}")
        if not all(math.isfinite(x) for x in val):
            self.fail(key, f"must be finite, got {val!r}")
        return [float(x) for x in val]

    def nonzero_vector(self, key, default):
        val = self.vector(key, default)
        if not any(val):
            self.fail(key, "must be non-zero")
        return val

    def direction(self, key, default):
        """A direction: 3 numbers, not all zero, or a keyword of the character's frame
        (:data:`neuromotor.model.facing.DIRECTION_KEYWORDS`), resolved when the run is built."""
        from neuromotor.model.facing import DIRECTION_KEYWORDS

        val = self.get(key, default)
        if isinstance(val, str):
            if val not in DIRECTION_KEYWORDS:
                self.fail(key, f"must be 3 numbers or one of {list(DIRECTION_KEYWORDS)}, got {val!r}")
            return val
        return self.nonzero_vector(key, default)

    def choice(self, key, default, options):
        val = self.get(key, default)
        if val not in options:
            self.fail(key, f"must be one of {list(options)}, got {val!r}")
        return val

    def boolean(self, key, default):
        val = self.get(key, default)
        if not isinstance(val, bool):
            self.fail(key, f"must be true or false, got {val!r}")
        return val

    def string(self, key, default, what: str = "a string"):
        val = self.get(key, default)
        if val is not None and not isinstance(val, str):
            self.fail(key, f"must be {what}, got {val!r}")
        return val

    def string_list(self, key, default):
        val = self.get(key, default)
        if not isinstance(val, list) or not all(isinstance(x, str) for x in val):
            self.fail(key, f"must be a list of strings, got {val!r}")
        return list(val)

    def path(self, key, default, base_dir, what: str = "a path string"):
        """A path string, relative to ``base_dir`` (the config's folder) unless absolute."""
        val = self.string(key, default, what)
        return None if val is None else resolve(val, base_dir)

    def tables(self, key, what: str) -> list | None:
        """An array of tables ``[[what]]``: None when absent, else a non-empty list."""
        val = self.get(key, None)
        if val is not None and (not isinstance(val, list) or not val):
            self.fail(key, f"must be an array of tables ([[{what}]])")
        return val

    def number_list(self, key, default, *, nonneg=False, allow_range=True):
        """A non-empty list of numbers or (``allow_range``) ``{start, stop, num, log}``."""
        val = self.get(key, default)
        if val is None:
            return None
        if isinstance(val, dict) and allow_range:
            vals = self._range(key, val)
        elif isinstance(val, list) and val and all(_is_number(x) and math.isfinite(x) for x in val):
            vals = val
        else:
            self.fail(
                key,
                f"must be a non-empty list of numbers{' or {start, stop, num}' if allow_range else ''}, got {val!r}",
            )
        if nonneg and any(v < 0 for v in vals):
            self.fail(key, "values must be >= 0")
        return [float(v) for v in vals]

    def _range(self, key, val: dict) -> list:
        r = Fields(val, self.name(key), self.source)
        start, stop, num = r.number("start", None), r.number("stop", None), r.get("num", None)
        log = r.boolean("log", False)
        r.done()
        if start is None or stop is None:
            self.fail(key, "needs start and stop")
        if isinstance(num, bool) or not isinstance(num, int) or num < 1:
            r.fail("num", f"must be a positive integer, got {num!r}")
        if log and not (start > 0 and stop > 0):
            self.fail(key, "log spacing needs start > 0 and stop > 0")
        return list(np.geomspace(start, stop, num) if log else np.linspace(start, stop, num))

    def done(self, allowed_tables=()):
        extra = set(self.table) - self.used - set(allowed_tables)
        if extra:
            self.fail(sorted(extra)[0], f"is not a known field (known: {sorted(self.used)})")


def resolve(path: str, base_dir) -> pathlib.Path:
    p = pathlib.Path(path)
    if base_dir is not None and not p.is_absolute():
        p = pathlib.Path(base_dir) / p
    return p
