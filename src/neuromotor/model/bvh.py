"""BVH motion-capture reader and writer (numpy only).

Grammar accepted
----------------
``HIERARCHY``, one ``ROOT name { ... }`` block holding ``OFFSET x y z``, ``CHANNELS n name...``,
nested ``JOINT name { ... }`` blocks and at most one ``End Site { OFFSET x y z }`` per joint; then
``MOTION``, ``Frames: N``, ``Frame Time: t`` and N lines of numbers, one frame per line. Tokens may
be separated by any mix of spaces and tabs, lines may end in LF, CRLF or CR, braces may sit on their
own line or after the keyword, keywords are case-insensitive, blank lines (notably at the end) and
trailing whitespace are ignored. A joint has 0 or 3 rotation channels and 0 or 3 position channels
(each axis once, any order, any joint); a joint without a CHANNELS line has no channels. Anything
else raises :class:`BvhError`, whose text is ``PATH:LINE: message``. A joint's name is the rest
of its ROOT/JOINT line, inner whitespace collapsed to single spaces. Frame lines must each hold
exactly one frame; blank lines among them are skipped. Fewer frame lines than ``Frames`` declares is
an error; more (common in exported files) are all loaded, and :attr:`BvhClip.warnings` records it as
``PATH:LINE: N more frame lines than 'Frames: M' declares; loaded all K`` (LINE: the first extra line).

Units
-----
Lengths (OFFSETs, End Sites, position channels) are stored in metres: file value times
``length_scale``. Rotation channels stay in degrees, as in the file. ``units`` is a key of
:data:`neuromotor.model.units.UNIT_SCALES` (m, cm, mm, in, cmu = CMU's 1/0.45 inch, ft, dm), a
positive float (metres per file unit) or ``"auto"``. Humanoid clips get their unit from the stature
their long bones give (:func:`neuromotor.model.anatomy.prepare_clip`, which reads files with
``units=1.0``); this module's own ``"auto"`` rule (:func:`neuromotor.model.units.auto_scale`), used
for skeletons that are not humanoid: place the skeleton in its rest pose (all rotations zero, the
root at the origin, i.e. the root OFFSET is ignored), take the diagonal of the bounding box of all
joint and End Site positions as its size in file units, and choose among m, cm and mm the scale
whose size in metres is closest to 1.8 m in log ratio (smallest ``|log(size * scale / 1.8)|``; ties
go to the larger unit). A skeleton of zero size is taken to be in metres. Inches are never guessed:
pass ``units="in"``.

Conventions (this module only stores data; kinematics live elsewhere)
---------------------------------------------------------------------
* Translation: for any joint with position channels, the channel values *replace* its OFFSET as the
  joint's translation in its parent's frame (Blender's convention; files commonly set the root
  OFFSET equal to the first frame's position). Joints without position channels are translated by
  their OFFSET.
* Rotation: the rotation channels are Euler angles in degrees applied in file order as intrinsic
  rotations, ``R = R_a1(v1) @ R_a2(v2) @ R_a3(v3)`` for channels ``a1 a2 a3``, and a point in the
  joint's frame maps to its parent's frame as ``p_parent = R @ p_joint + translation``.
* Columns: ``motion`` has one column per channel, joints in file (depth-first) order, channels in
  file order within a joint; ``BvhJoint.channel_start`` is a joint's first column.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
from collections.abc import Callable
from typing import NoReturn

import numpy as np

from neuromotor.atomic import atomic_path
from neuromotor.errors import UserError
from neuromotor.model.units import auto_scale, resolve_units

_Fail = Callable[[int | None, str], NoReturn]  # raises a BvhError naming the line

__all__ = [
    "BvhError",
    "BvhJoint",
    "BvhClip",
    "parse_bvh",
    "read_bvh",
    "write_bvh",
    "rest_pose_positions",
]

_CHANNEL_RE = re.compile(r"^([xyz])(position|rotation)$", re.IGNORECASE)
_FRAMES_RE = re.compile(r"^frames\s*:\s*(.*)$", re.IGNORECASE)
_FRAME_TIME_RE = re.compile(r"^frame\s+time\s*:\s*(.*)$", re.IGNORECASE)
_BRACE_SPLIT_RE = re.compile(r"([{}])")
_BRACES = frozenset("{}")


class BvhError(UserError):
    """Malformed BVH. ``str(e)`` is ``'PATH:LINE: message'`` (``'PATH: message'`` without a line).

    Attributes: ``path`` (str), ``line`` (1-based int or None), ``message`` (str).
    """

    def __init__(self, path: str, line: int | None, message: str):
        self.path = str(path)
        self.line = line
        self.message = message
        where = self.path if line is None else f"{self.path}:{line}"
        super().__init__(f"{where}: {message}")

    def __reduce__(self):  # keep the three attributes through pickling (multiprocessing)
        return (type(self), (self.path, self.line, self.message))


def _channel_kinds(channels: tuple[str, ...]) -> list[tuple[str, str]]:
    """[(axis 'X'|'Y'|'Z', 'position'|'rotation')] per channel; assumes valid names."""
    out = []
    for name in channels:
        m = _CHANNEL_RE.match(name)
        assert m is not None  # names checked by _parse_channels
        out.append((m.group(1).upper(), m.group(2).lower()))
    return out


def _channel_problem(channels: tuple[str, ...] | list[str]) -> str | None:
    """Why this channel list is not valid BVH, or None if it is."""
    seen: dict[str, list[str]] = {"position": [], "rotation": []}
    for name in channels:
        m = _CHANNEL_RE.match(name)
        if m is None:
            return (
                f"unknown channel name {name!r} (expected Xposition, Yposition, Zposition, "
                f"Xrotation, Yrotation or Zrotation)"
            )
        axis, kind = m.group(1).upper(), m.group(2).lower()
        if axis in seen[kind]:
            return f"duplicate {axis}{kind} channel ({name!r})"
        seen[kind].append(axis)
    for kind, axes in seen.items():
        if len(axes) not in (0, 3):
            return (
                f"{len(axes)} {kind} channel{'s' if len(axes) != 1 else ''} "
                f"({' '.join(a + kind for a in axes)}); a joint needs 0 or 3 {kind} channels"
            )
    return None


def _vec3(value, what: str) -> np.ndarray:
    arr = np.array(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,):
        raise ValueError(f"{what} must have 3 components, got shape {np.shape(value)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be finite, got {arr}")
    arr.setflags(write=False)
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class BvhJoint:
    """One ROOT or JOINT of the hierarchy. Lengths in metres."""

    name: str
    parent: int  # index into BvhClip.joints; -1 for the root
    offset: np.ndarray  # (3,) metres
    channels: tuple[str, ...]  # as spelled in the file
    channel_start: int  # column of the first channel in BvhClip.motion
    end_site: np.ndarray | None = None  # (3,) metres, or None
    line: int = 0  # 1-based line of the ROOT/JOINT keyword (0: not from a file)

    def __post_init__(self) -> None:
        object.__setattr__(self, "offset", _vec3(self.offset, f"joint {self.name!r} offset"))
        if self.end_site is not None:
            object.__setattr__(self, "end_site", _vec3(self.end_site, f"joint {self.name!r} End Site"))
        channels = tuple(str(c) for c in self.channels)
        object.__setattr__(self, "channels", channels)
        problem = _channel_problem(channels)
        if problem is not None:
            raise ValueError(f"joint {self.name!r}: {problem}")

    @property
    def rotation_order(self) -> str:
        """Axes of the rotation channels in file order, e.g. ``"ZXY"``; ``""`` if none."""
        return "".join(axis for axis, kind in _channel_kinds(self.channels) if kind == "rotation")

    @property
    def rotation_columns(self) -> tuple[int, ...]:
        """Absolute motion columns of the rotation channels, in file order."""
        return tuple(
            self.channel_start + i for i, (_, kind) in enumerate(_channel_kinds(self.channels)) if kind == "rotation"
        )

    @property
    def translation_columns(self) -> tuple[int, ...]:
        """Absolute motion columns of Xposition, Yposition, Zposition in X, Y, Z order; () if none."""
        cols = {
            axis: self.channel_start + i
            for i, (axis, kind) in enumerate(_channel_kinds(self.channels))
            if kind == "position"
        }
        return tuple(cols[a] for a in "XYZ") if cols else ()


@dataclasses.dataclass(frozen=True, eq=False)
class BvhClip:
    """A parsed BVH file: hierarchy plus motion (positions in metres, rotations in degrees).

    Arrays are copied to float64 and made read-only on construction. ``joints`` must be in
    depth-first pre-order (a parent before its children, subtrees contiguous) with contiguous
    ``channel_start`` values, as in a file; ``motion`` must be ``(T >= 1, n_channels)``.
    """

    path: str
    joints: tuple[BvhJoint, ...]  # file (depth-first) order; joints[0] is the root
    frame_time: float  # seconds
    motion: np.ndarray  # (T, C)
    length_scale: float = 1.0  # metres per file length unit
    warnings: tuple[str, ...] = dataclasses.field(default=(), compare=False)  # one line each, from parsing

    def __post_init__(self) -> None:
        object.__setattr__(self, "warnings", tuple(str(w) for w in self.warnings))
        joints = tuple(self.joints)
        object.__setattr__(self, "joints", joints)
        object.__setattr__(self, "path", str(self.path))
        _check_joint_layout(joints)
        n_channels = sum(len(j.channels) for j in joints)
        motion = np.array(self.motion, dtype=np.float64)
        if motion.ndim != 2 or motion.shape[0] < 1 or motion.shape[1] != n_channels:
            raise ValueError(f"motion must have shape (T >= 1, {n_channels}), got {motion.shape}")
        motion.setflags(write=False)
        object.__setattr__(self, "motion", motion)
        frame_time = float(self.frame_time)
        if not (math.isfinite(frame_time) and frame_time > 0):
            raise ValueError(f"frame_time must be a positive number of seconds, got {self.frame_time!r}")
        object.__setattr__(self, "frame_time", frame_time)
        scale = float(self.length_scale)
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"length_scale must be positive, got {self.length_scale!r}")
        object.__setattr__(self, "length_scale", scale)

    @property
    def n_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def n_channels(self) -> int:
        return int(self.motion.shape[1])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    @property
    def duration(self) -> float:
        """Time from the first to the last frame, ``(T - 1) * frame_time`` seconds."""
        return (self.n_frames - 1) * self.frame_time

    def children(self, j: int) -> tuple[int, ...]:
        """Indices of the joints whose parent is ``j``, in file order."""
        return tuple(k for k, joint in enumerate(self.joints) if joint.parent == j)

    def joint_index(self, name: str) -> int:
        """Index of the joint called ``name``; KeyError listing the names if there is none."""
        for k, joint in enumerate(self.joints):
            if joint.name == name:
                return k
        raise KeyError(f"no joint named {name!r} in {self.path}; joints: {', '.join(j.name for j in self.joints)}")


def _check_joint_layout(joints: tuple[BvhJoint, ...]) -> None:
    """ValueError unless joints are a single tree in pre-order with contiguous channel columns."""
    if not joints:
        raise ValueError("a clip needs at least one joint")
    names: set[str] = set()
    ancestors: list[int] = []  # path from the root to the previous joint
    column = 0
    for k, joint in enumerate(joints):
        if not isinstance(joint, BvhJoint):
            raise ValueError(f"joints[{k}] is not a BvhJoint")
        if joint.name in names:
            raise ValueError(f"duplicate joint name {joint.name!r}")
        names.add(joint.name)
        if k == 0:
            if joint.parent != -1:
                raise ValueError("joints[0] must be the root (parent -1)")
        else:
            while ancestors and ancestors[-1] != joint.parent:
                ancestors.pop()
            if not ancestors:
                raise ValueError(
                    f"joints are not in depth-first order: joint {k} ({joint.name!r}) has "
                    f"parent {joint.parent}, which is not the previous joint or one of its ancestors"
                )
        ancestors.append(k)
        if joint.channel_start != column:
            raise ValueError(f"joint {joint.name!r} has channel_start {joint.channel_start}, expected {column}")
        column += len(joint.channels)


# --------------------------------------------------------------------------------------------
# Reading


def _split_lines(text: str) -> list[str]:
    # Explicit split so line numbers match editors (str.splitlines also splits on \x0c etc.).
    if text.startswith("\ufeff"):
        text = text[1:]
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def _line_tokens(line: str) -> list[str]:
    out: list[str] = []
    for tok in line.split():
        out.extend(part for part in _BRACE_SPLIT_RE.split(tok) if part)
    return out


def _short(text: str, n: int = 40) -> str:
    text = text.strip()
    return text if len(text) <= n else text[: n - 3] + "..."


def _parse_float(tok: str) -> float | None:
    try:
        return float(tok)
    except ValueError:
        return None


@dataclasses.dataclass
class _Node:
    """Mutable joint under construction (lengths still in file units)."""

    name: str
    parent: int
    line: int
    offset: tuple[float, float, float] | None = None
    channels: tuple[str, ...] | None = None
    end_site: tuple[float, float, float] | None = None
    end_site_line: int | None = None


@dataclasses.dataclass
class _Block:
    """An open ROOT/JOINT/End Site block on the parser's stack."""

    kind: str  # "joint" or "end"
    node: int
    line: int
    opened: bool = False
    offset: tuple[float, float, float] | None = None  # End Site offset

    def describe(self, nodes: list[_Node]) -> str:
        name = nodes[self.node].name
        return f"joint {name!r}" if self.kind == "joint" else f"End Site of joint {name!r}"


class _HierarchyParser:
    """The HIERARCHY section, token by token: braces open and close blocks, every other token
    starts a statement that runs to the end of the line or the next brace."""

    def __init__(self, fail: Callable[[int | None, str], NoReturn]):
        self.fail = fail
        self.nodes: list[_Node] = []
        self.first_line_of: dict[str, int] = {}
        self.stack: list[_Block] = []
        self.seen_hierarchy = False

    def brace_or_header(self, tok: str, lineno: int) -> bool:
        """Handle the HIERARCHY keyword and braces; False when ``tok`` starts a statement."""
        fail, stack = self.fail, self.stack
        if not self.seen_hierarchy:
            if tok.upper() != "HIERARCHY":
                fail(lineno, f"expected 'HIERARCHY' at the start of the file, got {tok!r}")
            self.seen_hierarchy = True
            return True
        if stack and not stack[-1].opened:
            if tok != "{":
                fail(
                    lineno,
                    f"expected '{{' to open {stack[-1].describe(self.nodes)} (line {stack[-1].line}), got {tok!r}",
                )
            stack[-1].opened = True
            return True
        if tok == "{":
            fail(lineno, "unexpected '{'")
        if tok == "}":
            if not stack:
                fail(lineno, "unmatched '}'")
            _close_block(stack.pop(), self.nodes, self.fail)
            return True
        return False

    def motion(self, toks: list[str], lineno: int) -> None:
        """Check that MOTION may come here."""
        top = self.stack[-1] if self.stack else None
        if top is not None:
            self.fail(
                lineno,
                f"MOTION inside the hierarchy: {top.describe(self.nodes)} opened at line "
                f"{top.line} is missing its closing '}}'",
            )
        if not self.nodes:
            self.fail(lineno, "MOTION before any ROOT")
        if len(toks) > 1:
            self.fail(lineno, f"unexpected text after MOTION: {_short(' '.join(toks[1:]))!r}")

    def statement(self, word: str, tok: str, args: list[str], toks: list[str], k: int, end: int, lineno: int) -> None:
        top = self.stack[-1] if self.stack else None
        if word in ("ROOT", "JOINT"):
            self.joint(word, tok, args, top, lineno)
        elif word == "END":
            self.end_site(args, toks[k:end], top, lineno)
        elif word == "OFFSET":
            self.offset(args, top, lineno)
        elif word == "CHANNELS":
            self.channels(args, top, lineno)
        else:
            context = "in the hierarchy" if self.stack else "between blocks"
            self.fail(lineno, f"unexpected {_short(tok)!r} {context}")

    def joint(self, word: str, tok: str, args: list[str], top: _Block | None, lineno: int) -> None:
        fail, nodes = self.fail, self.nodes
        if word == "ROOT":
            if nodes:
                fail(
                    lineno,
                    f"several ROOTs: only one skeleton per file is supported "
                    f"(first ROOT {nodes[0].name!r} at line {nodes[0].line})",
                )
            parent = -1
        else:
            if top is None:
                where = "before ROOT" if not nodes else "after the ROOT block was closed"
                fail(lineno, f"JOINT {where}")
            if top.kind == "end":
                fail(lineno, f"JOINT inside the {top.describe(nodes)} (line {top.line})")
            parent = top.node
        if not args:
            fail(lineno, f"{tok} without a name")
        name = " ".join(args)
        if name in self.first_line_of:
            fail(lineno, f"duplicate joint name {name!r} (first defined at line {self.first_line_of[name]})")
        self.first_line_of[name] = lineno
        nodes.append(_Node(name=name, parent=parent, line=lineno))
        self.stack.append(_Block("joint", len(nodes) - 1, lineno))

    def end_site(self, args: list[str], statement: list[str], top: _Block | None, lineno: int) -> None:
        fail = self.fail
        if len(args) != 1 or args[0].upper() != "SITE":
            fail(lineno, f"expected 'End Site', got {_short(' '.join(statement))!r}")
        if top is None or top.kind != "joint":
            fail(lineno, "End Site outside a joint")
        node = self.nodes[top.node]
        if node.end_site_line is not None:
            fail(lineno, f"joint {node.name!r} has a second End Site (first at line {node.end_site_line})")
        node.end_site_line = lineno
        self.stack.append(_Block("end", top.node, lineno))

    def offset(self, args: list[str], top: _Block | None, lineno: int) -> None:
        fail = self.fail
        if top is None:
            fail(lineno, "OFFSET outside a joint")
        values = _parse_offset(args, lineno, fail)
        if top.kind == "end":
            if top.offset is not None:
                fail(lineno, f"second OFFSET in the {top.describe(self.nodes)}")
            top.offset = values
        else:
            node = self.nodes[top.node]
            if node.offset is not None:
                fail(lineno, f"second OFFSET in joint {node.name!r}")
            node.offset = values

    def channels(self, args: list[str], top: _Block | None, lineno: int) -> None:
        fail = self.fail
        if top is None:
            fail(lineno, "CHANNELS outside a joint")
        if top.kind == "end":
            fail(lineno, "an End Site cannot have CHANNELS")
        node = self.nodes[top.node]
        if node.channels is not None:
            fail(lineno, f"second CHANNELS line in joint {node.name!r}")
        node.channels = _parse_channels(args, lineno, fail)

    def no_motion(self, lines: list[str]) -> NoReturn:
        """The file ended before MOTION: say what is missing."""
        last = _last_text_line(lines)
        if not self.seen_hierarchy:
            self.fail(last, "empty file: expected 'HIERARCHY'")
        if self.stack:
            self.fail(
                last,
                f"unexpected end of file inside the hierarchy: {self.stack[-1].describe(self.nodes)} "
                f"opened at line {self.stack[-1].line} is not closed",
            )
        if not self.nodes:
            self.fail(last, "no ROOT in the hierarchy")
        self.fail(last, "missing MOTION section after the hierarchy")


def _parse_hierarchy(lines: list[str], fail: Callable[[int | None, str], NoReturn]) -> tuple[list[_Node], int]:
    """Parse up to and including the MOTION line; return the joints and MOTION's 0-based line index."""
    parser = _HierarchyParser(fail)
    for index, raw in enumerate(lines):
        lineno = index + 1
        toks = _line_tokens(raw)
        k = 0
        while k < len(toks):
            tok = toks[k]
            if parser.brace_or_header(tok, lineno):
                k += 1
                continue
            # A statement: keyword plus the rest of the line up to the next brace.
            end = k + 1
            while end < len(toks) and toks[end] not in _BRACES:
                end += 1
            if tok.upper() == "MOTION":
                parser.motion(toks, lineno)
                return parser.nodes, index
            parser.statement(tok.upper(), tok, toks[k + 1 : end], toks, k, end, lineno)
            k = end
    parser.no_motion(lines)


def _close_block(block: _Block, nodes: list[_Node], fail: Callable[[int | None, str], NoReturn]) -> None:
    node = nodes[block.node]
    if block.kind == "end":
        if block.offset is None:
            fail(block.line, f"End Site of joint {node.name!r} has no OFFSET")
        node.end_site = block.offset
    else:
        if node.offset is None:
            fail(block.line, f"joint {node.name!r} has no OFFSET")
        if node.channels is None:
            node.channels = ()


def _parse_offset(args: list[str], lineno: int, fail: _Fail) -> tuple[float, float, float]:
    if len(args) != 3:
        fail(lineno, f"OFFSET needs 3 numbers, got {len(args)}")
    values = []
    for tok in args:
        value = _parse_float(tok)
        if value is None:
            fail(lineno, f"OFFSET value {tok!r} is not a number")
        if not math.isfinite(value):
            fail(lineno, f"OFFSET value {tok!r} is not finite")
        values.append(value)
    return (values[0], values[1], values[2])


def _parse_channels(args: list[str], lineno: int, fail: _Fail) -> tuple[str, ...]:
    if not args:
        fail(lineno, "CHANNELS without a count")
    try:
        count = int(args[0])
    except ValueError:
        fail(lineno, f"CHANNELS count {args[0]!r} is not an integer")
    names = tuple(args[1:])
    if count != len(names):
        fail(lineno, f"CHANNELS declares {count} channels but lists {len(names)}")
    problem = _channel_problem(names)
    if problem is not None:
        fail(lineno, problem)
    return names


def _last_text_line(lines: list[str]) -> int:
    for index in range(len(lines) - 1, -1, -1):
        if lines[index].strip():
            return index + 1
    return 1


def _header_value(lines: list[str], index: int, pattern: re.Pattern, expected: str, fail: _Fail) -> str:
    """The value of a MOTION header line (``Frames: N``, ``Frame Time: t``), or a failure
    quoting the line."""
    m = pattern.match(lines[index].strip())
    if m is None:
        fail(index + 1, f"expected '{expected}', got {_short(lines[index])!r}")
    return m.group(1).strip()


def _parse_frame_count(lines: list[str], index: int, fail: _Fail) -> int:
    value = _header_value(lines, index, _FRAMES_RE, "Frames: N", fail)
    try:
        n_frames = int(value)
    except ValueError:
        fail(index + 1, f"invalid frame count {value!r} (expected 'Frames: N' with an integer N)")
    if n_frames <= 0:
        fail(index + 1, f"Frames: {n_frames}: a clip needs at least one frame")
    return n_frames


def _parse_frame_time(lines: list[str], index: int, fail: _Fail) -> float:
    value = _header_value(lines, index, _FRAME_TIME_RE, "Frame Time: t", fail)
    frame_time = _parse_float(value)
    if frame_time is None or not math.isfinite(frame_time):
        fail(index + 1, f"invalid Frame Time {value!r} (expected a positive number of seconds)")
    if frame_time <= 0:
        fail(index + 1, f"Frame Time must be positive, got {value}")
    return frame_time


def _parse_frame(
    toks: list[str], lineno: int, row: int, n_channels: int, n_frames: int, last_line: bool, fail
) -> list[float]:
    """One frame line's values, checked: numbers, one per channel, finite."""
    try:
        values = [float(t) for t in toks]
    except ValueError:
        for col, tok in enumerate(toks):
            if _parse_float(tok) is None:
                fail(lineno, f"frame {row + 1}, value {col + 1}: {_short(tok)!r} is not a number")
        raise  # unreachable: some token failed above
    if len(values) != n_channels:
        if len(values) < n_channels and last_line and row < n_frames:
            fail(
                lineno,
                f"truncated motion block: data ends here inside frame {row + 1} "
                f"({len(values)} of {n_channels} values); expected {n_frames} frames, "
                f"found {row} complete",
            )
        fail(lineno, f"frame {row + 1} has {len(values)} values, expected {n_channels} (one per channel)")
    bad = [c for c, v in enumerate(values) if not math.isfinite(v)]
    if bad:
        fail(
            lineno,
            f"frame {row + 1}, value {bad[0] + 1}: {toks[bad[0]]!r} is not finite "
            f"(NaN and infinite values are not allowed)",
        )
    return values


def _parse_motion(
    lines: list[str],
    motion_index: int,
    n_channels: int,
    fail: Callable[[int | None, str], NoReturn],
    path: str = "<string>",
) -> tuple[float, np.ndarray, tuple[str, ...]]:
    """Parse Frames, Frame Time and the frame lines after the MOTION line; values in file units.
    Returns (frame time, motion, warnings)."""
    data_lines = [i for i in range(motion_index + 1, len(lines)) if lines[i].strip()]
    last = data_lines[-1] + 1 if data_lines else motion_index + 1
    if not data_lines:
        fail(last, "unexpected end of file after MOTION: expected 'Frames: N'")
    frames_index = data_lines[0]
    n_frames = _parse_frame_count(lines, frames_index, fail)
    if len(data_lines) < 2:
        fail(last, "unexpected end of file: expected 'Frame Time: t'")
    frame_time = _parse_frame_time(lines, data_lines[1], fail)
    if n_channels == 0:
        fail(data_lines[1] + 1, "the hierarchy declares no channels, so frames cannot carry data")

    frame_indices = data_lines[2:]
    # Size by the lines present, not by the declared count (a bogus huge Frames must not allocate).
    motion = np.empty((len(frame_indices), n_channels), dtype=np.float64)
    for row, index in enumerate(frame_indices):
        motion[row] = _parse_frame(
            lines[index].split(), index + 1, row, n_channels, n_frames, index == data_lines[-1], fail
        )
    if len(frame_indices) < n_frames:
        fail(
            last,
            f"truncated motion block: 'Frames: {n_frames}' (line {frames_index + 1}) declares "
            f"{n_frames} frames but the data ends at this line after {len(frame_indices)}",
        )
    warnings: tuple[str, ...] = ()
    if len(frame_indices) > n_frames:
        extra = len(frame_indices) - n_frames
        warnings = (
            f"{path}:{frame_indices[n_frames] + 1}: {extra} more frame line{'s' if extra != 1 else ''} "
            f"than 'Frames: {n_frames}' declares; loaded all {len(frame_indices)}",
        )
    return frame_time, motion, warnings


def _rest_points(
    offsets: np.ndarray, parents: list[int], end_sites: list[np.ndarray | None], root_at: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Rest-pose joint positions (J, 3) and End Site positions (E, 3), root placed at ``root_at``."""
    pos = np.zeros((len(parents), 3), dtype=np.float64)
    for k, parent in enumerate(parents):
        pos[k] = root_at if parent < 0 else pos[parent] + offsets[k]
    ends = [pos[k] + e for k, e in enumerate(end_sites) if e is not None]
    return pos, np.array(ends, dtype=np.float64).reshape(-1, 3)


def parse_bvh(text: str, path: str = "<string>", units: str | float = "auto") -> BvhClip:
    """Parse BVH text into a :class:`BvhClip` (lengths in metres, see the module docstring).

    ``path`` is only used in error messages and stored in the clip. Raises :class:`BvhError` on a
    malformed file and ValueError on a bad ``units``.
    """
    path = str(path)
    fixed_scale = resolve_units(units)

    def fail(line: int | None, message: str) -> NoReturn:
        raise BvhError(path, line, message)

    lines = _split_lines(text)
    nodes, motion_index = _parse_hierarchy(lines, fail)
    n_channels = sum(len(n.channels or ()) for n in nodes)  # () once the block closed
    frame_time, motion, warnings = _parse_motion(lines, motion_index, n_channels, fail, path)

    offsets = np.array([n.offset for n in nodes], dtype=np.float64)
    parents = [n.parent for n in nodes]
    end_sites = [None if n.end_site is None else np.array(n.end_site, dtype=np.float64) for n in nodes]
    scale = (
        fixed_scale
        if fixed_scale is not None
        else auto_scale(np.concatenate(_rest_points(offsets, parents, end_sites, np.zeros(3))))
    )

    joints = []
    column = 0
    for node, end_site in zip(nodes, end_sites):
        channels = node.channels or ()  # () once the block closed
        kinds = _channel_kinds(channels)
        for i, (_, kind) in enumerate(kinds):
            if kind == "position":
                motion[:, column + i] *= scale
        joints.append(
            BvhJoint(
                name=node.name,
                parent=node.parent,
                offset=np.array(node.offset, dtype=np.float64) * scale,
                channels=channels,
                channel_start=column,
                end_site=None if end_site is None else end_site * scale,
                line=node.line,
            )
        )
        column += len(channels)
    return BvhClip(
        path=path, joints=tuple(joints), frame_time=frame_time, motion=motion, length_scale=scale, warnings=warnings
    )


def read_bvh(path: str | os.PathLike, units: str | float = "auto") -> BvhClip:
    """Read a BVH file (UTF-8, falling back to Latin-1) and parse it with :func:`parse_bvh`."""
    resolve_units(units)  # fail on a bad argument before touching the disk
    with open(path, "rb") as fh:
        data = fh.read()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    return parse_bvh(text, path=os.fspath(path), units=units)


# --------------------------------------------------------------------------------------------
# Writing


def _format_number(value: float, precision: int) -> str:
    text = f"{value:.{precision}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text == "-0" else text


def _format_bvh(clip: BvhClip, motion: np.ndarray, precision: int) -> str:
    scale = clip.length_scale

    def vec(v: np.ndarray) -> str:
        return " ".join(_format_number(float(x) / scale, precision) for x in v)

    out = ["HIERARCHY"]
    open_joints: list[int] = []

    def close() -> None:
        k = open_joints.pop()
        pad = "\t" * len(open_joints)
        joint = clip.joints[k]
        if joint.end_site is not None:
            out.extend([f"{pad}\tEnd Site", f"{pad}\t{{", f"{pad}\t\tOFFSET {vec(joint.end_site)}", f"{pad}\t}}"])
        out.append(f"{pad}}}")

    for k, joint in enumerate(clip.joints):
        while open_joints and open_joints[-1] != joint.parent:
            close()
        pad = "\t" * len(open_joints)
        out.append(f"{pad}{'ROOT' if k == 0 else 'JOINT'} {joint.name}")
        out.append(f"{pad}{{")
        out.append(f"{pad}\tOFFSET {vec(joint.offset)}")
        out.append(f"{pad}\tCHANNELS {len(joint.channels)}" + "".join(" " + c for c in joint.channels))
        open_joints.append(k)
    while open_joints:
        close()

    out += ["MOTION", f"Frames: {motion.shape[0]}", f"Frame Time: {clip.frame_time!r}"]
    file_values = motion.copy()
    for joint in clip.joints:
        cols = list(joint.translation_columns)
        file_values[:, cols] /= scale
    for row in file_values:
        out.append(" ".join(_format_number(float(x), precision) for x in row))
    out.append("")
    return "\n".join(out)


def _atomic_write(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to a temp file beside ``path`` and rename it over ``path`` (see
    :func:`neuromotor.atomic.atomic_path`: an existing file's mode is kept, signals clean up;
    the folder must exist)."""
    with atomic_path(path, make_parents=False) as tmp:
        tmp.write_bytes(data)


def write_bvh(path: str | os.PathLike, clip: BvhClip, motion: np.ndarray | None = None, precision: int = 8) -> None:
    """Write ``clip`` (or its hierarchy with ``motion``, shape (T, C), positions in metres) as BVH.

    Lengths are divided by ``clip.length_scale`` back to file units; rotations are written in
    degrees; every number gets at most ``precision`` decimals (trailing zeros dropped); Frame Time
    is written as the shortest text that reads back as the same float. LF line ends, tab indents.
    The file is replaced atomically: everything is validated and formatted first, then written to a
    temporary file in the same directory and renamed, so a failure leaves no partial file behind.
    """
    if isinstance(precision, bool) or not isinstance(precision, (int, np.integer)) or not 0 <= precision <= 20:
        raise ValueError(f"precision must be an integer number of decimals in [0, 20], got {precision!r}")
    values = clip.motion if motion is None else np.asarray(motion, dtype=np.float64)
    if values.ndim != 2 or values.shape[0] < 1 or values.shape[1] != clip.n_channels:
        raise ValueError(f"motion must have shape (T >= 1, {clip.n_channels}), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError("motion contains NaN or infinite values")
    for joint in clip.joints:
        name = joint.name
        if not name or " ".join(name.split()) != name or any(c in name for c in "{}"):
            raise ValueError(
                f"joint name {name!r} cannot be written to BVH (empty, braces, or "
                f"whitespace other than single inner spaces)"
            )
    text = _format_bvh(clip, values, int(precision))
    _atomic_write(path, text.encode("utf-8"))


def rest_pose_positions(clip: BvhClip) -> np.ndarray:
    """(J, 3) joint positions in metres in the zero-rotation rest pose built from the OFFSETs,
    the root placed at its own OFFSET (position channels are not used)."""
    offsets = np.array([j.offset for j in clip.joints], dtype=np.float64)
    parents = [j.parent for j in clip.joints]
    pos, _ = _rest_points(offsets, parents, [None] * len(parents), offsets[0])
    return pos
