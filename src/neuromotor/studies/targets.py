"""Targets for gain calibration: recovery trajectories read from files, and response features.

Trajectory files
----------------
A trajectory target is a time series of joint angles (all DOFs or a named subset) or of body
COM positions after a perturbation. Times are clip times in seconds (the same clock as
``sim.start`` and the perturbations' ``start``); the target is linearly interpolated onto the
simulation grid inside the fit window, which must lie inside the file's time span.

NPZ layout::

    time    (T,)                 seconds, strictly increasing
    names   (k,)  str            DOF names ("Chest.Zrotation") or body names ("Chest2")
    values  (T, k) or (C, T, k)  joint angles, one slice per perturbation case C
            (T, k, 3) or (C, T, k, 3) body positions (world, metres)

CSV layout (one header row, comma separated, ``#`` lines are comments)::

    case,time,Chest.Zrotation,Chest.Xrotation,...        joint angles
    case,time,Chest2.x,Chest2.y,Chest2.z,...             body positions (m)

``case`` (optional; default 0 for every row) is the 0-based index of the ``[[perturbation]]``
the row belongs to; every case must list the same times. Angles are radians unless the config
says ``angle_unit = "deg"``.

Corridors (joint angles): mean and standard deviation over subjects as functions of time, a
``NAME`` and a ``NAME.sd`` column for every DOF (``case,time,Chest.Xrotation,Chest.Xrotation.sd,...``;
sd > 0, in the same unit as the mean). Each sample's residual is weighted by 1 / sd(t), so the
fit counts misses in standard deviations and a wide corridor pulls less than a narrow one.

Recorded trials (BVH): a BVH of the perturbed trial on the same skeleton (the recorded reaction)
gives every non-root rotation channel as a joint-angle column named ``JOINT.Zrotation``, read in
the file's degrees and unwrapped in time; frame 0 sits at clip time ``time_offset`` (the
``[fit.target]`` field, default 0: the trial shares the clip's clock). :func:`match_trial` then
puts it on the model: the simulated DOFs only, in the clip's Euler orders (a joint written in
another order is decomposed again from its rotation), on the mocap's angle branch; channels of
joints the model does not simulate (toes, fingers, face, the driven root) are left out and
counted; another skeleton, length unit or an incommensurate frame time is refused.

Feature targets
---------------
Numbers such as the peak deviation after a push, given per perturbation case with a standard
deviation; see :data:`FEATURES`. Features are computed from the deviation signal d(t) in
degrees over the joints of a set of DOFs: by default the RMS over those joints of the geodesic
angle between the perturbed and unperturbed local rotations (the turn about the named axes
when only some of a joint's DOFs are listed; ``[sim] metric = "euler"``: the former per-DOF
``rms_i wrap(theta_i - theta_unperturbed_i)``; see :mod:`neuromotor.studies.metrics`), and the
peak acceleration from ``a(t)``, the RMS over the same joints of the time derivative of the
relative angular velocity difference in deg/s^2 (a central difference of the simulated joint
rates), with smooth surrogates so the fit can differentiate them.

Trajectory targets (the files above, recorded BVH trials, corridors) stay per Euler DOF: they
give Euler angles, and the residuals are simulated minus target angles in radians.

Body targets
------------
``body_angle`` and ``body_position`` (:mod:`neuromotor.studies.fit.observables`) read one series
per case from CSV (:func:`read_series`): a ``time`` column in the config's ``time_unit`` (ms or
s), one data column (the config's ``column``, or the file's only one) in its ``angle_unit`` or
``length_unit``, optionally its ``NAME.sd`` (a corridor) and a ``case`` column (0-based; or one
file per case, ``files = [...]``)::

    time,head,head.sd
    0,0.0,0.5
    10,0.4,0.6

Time 0 of the file sits at clip time ``time_offset`` (default: the case's onset).
"""

from __future__ import annotations

import csv
import dataclasses
import pathlib
from typing import TYPE_CHECKING

import numpy as np

from neuromotor.atomic import atomic_path
from neuromotor.config import ConfigError
from neuromotor.config.specs import TIME_UNITS

if TYPE_CHECKING:
    from neuromotor.model.bvh import BvhClip

FEATURES = {
    "peak_deviation_deg": "largest deviation d(t) (deg)",
    "time_to_peak_s": "time of the peak after the perturbation's start (s)",
    "recovery_time_s": "time after the start until d(t) stays below the threshold (s)",
    "overshoot_deg": "largest deviation after d(t) first returns below the threshold (deg)",
    "peak_acceleration_deg_s2": "largest a(t), the RMS over the joints of d/dt of the relative angular velocity "
    "difference (deg/s^2)",
}
AXES = ("x", "y", "z")
SD_SUFFIX = ".sd"  # corridor columns: NAME (mean over subjects) and NAME.sd (their standard deviation)


@dataclasses.dataclass
class TargetTable:
    """A trajectory target as read from disk, before matching to a model."""

    time: np.ndarray  # (T,)
    names: tuple[str, ...]  # DOF or body names
    values: np.ndarray  # (C, T, k) angles or (C, T, k, 3) positions
    quantity: str  # "joint_angles" | "body_positions"
    source: str
    sd: np.ndarray | None = None  # corridor: standard deviation over subjects, same shape as values
    radians: bool = False  # angles already in radians whatever the config's angle_unit (BVH)
    bvh: BvhClip | None = None  # BVH trial: the parsed file (file units), until match_trial puts it on the model
    not_fitted: str = ""  # BVH trial: the channels match_trial left out, one line for the fit's summary
    converted: str = ""  # BVH trial: the joints match_trial read in another Euler order, one line


def _fail(source, field, msg):
    raise ConfigError(f"{source}: field '{field}' {msg}")


def read_target(path, quantity: str = "joint_angles", time_offset: float = 0.0) -> TargetTable:
    """Read an NPZ, CSV or BVH trajectory target (layout in the module docstring); a BVH's frame
    0 is at clip time ``time_offset``."""
    path = pathlib.Path(path)
    src = str(path)
    if not path.exists():
        raise ConfigError(f"{src}: target file not found")
    if quantity not in ("joint_angles", "body_positions"):
        raise ValueError(f"quantity must be joint_angles or body_positions, got {quantity!r}")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        table = _read_npz(path, quantity)
    elif suffix == ".csv":
        table = _read_csv(path, quantity)
    elif suffix == ".bvh":
        table = _read_bvh(path, quantity, time_offset)
    else:
        raise ConfigError(f"{src}: target file must be .npz, .csv or .bvh, got {path.suffix!r}")
    t = table.time
    if t.ndim != 1 or t.size < 2 or not np.all(np.isfinite(t)) or not np.all(np.diff(t) > 0):
        _fail(src, "time", "must be a strictly increasing finite 1-D array with at least 2 samples")
    if not np.all(np.isfinite(table.values)):
        _fail(src, "values", "contains NaN or infinite entries")
    if table.sd is not None and not (np.all(np.isfinite(table.sd)) and np.all(table.sd > 0)):
        c, t, k = np.argwhere(~(np.isfinite(table.sd) & (table.sd > 0)))[0]
        _fail(
            src,
            f"{table.names[k]}.sd",
            f"must be finite and > 0 (case {c}, time {table.time[t]:g} s: {table.sd[c, t, k]!r})",
        )
    if len(set(table.names)) != len(table.names):
        _fail(src, "names", "contains duplicates")
    return table


def _read_npz(path, quantity) -> TargetTable:
    src = str(path)
    try:
        data = np.load(path, allow_pickle=False)
    except Exception as e:  # zipfile / numpy errors
        raise ConfigError(f"{src}: cannot read NPZ target: {e}") from None
    for key in ("time", "names", "values"):
        if key not in data.files:
            _fail(src, key, f"is missing (keys present: {sorted(data.files)})")
    time = np.asarray(data["time"], np.float64)
    names = tuple(str(n) for n in np.atleast_1d(data["names"]))
    values = np.asarray(data["values"], np.float64)
    raw_shape = values.shape
    k = len(names)
    if quantity == "joint_angles":
        if values.ndim == 2:
            values = values[None]
        want = f"(T, k) or (C, T, k) with T = {time.size}, k = {k}"
        if values.ndim != 3 or values.shape[1:] != (time.size, k):
            _fail(src, "values", f"has shape {raw_shape}; expected {want}")
    else:
        if values.ndim == 3:
            values = values[None]
        want = f"(T, k, 3) or (C, T, k, 3) with T = {time.size}, k = {k}"
        if values.ndim != 4 or values.shape[1:] != (time.size, k, 3):
            _fail(src, "values", f"has shape {raw_shape}; expected {want}")
    return TargetTable(time, names, values, quantity, src)


def _read_csv(path, quantity) -> TargetTable:
    src = str(path)
    with open(path, newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise ConfigError(f"{src}: empty CSV target")
    header = [h.strip() for h in rows[0]]
    if "time" not in header:
        _fail(src, "time", f"column is missing (header: {header})")
    data = rows[1:]
    if not data:
        raise ConfigError(f"{src}: CSV target has a header but no rows")
    try:
        arr = np.array([[float(x) for x in r] for r in data], np.float64)
    except ValueError as e:
        raise ConfigError(f"{src}: non-numeric entry in CSV target: {e}") from None
    if arr.shape[1] != len(header):
        raise ConfigError(f"{src}: rows have {arr.shape[1]} columns, header has {len(header)}")
    case = arr[:, header.index("case")].astype(int) if "case" in header else np.zeros(len(arr), int)
    data_cols = [i for i, h in enumerate(header) if h not in ("case", "time")]
    if not data_cols:
        raise ConfigError(f"{src}: CSV target has no data columns besides case/time")
    n_cases = int(case.max()) + 1
    if case.min() < 0 or set(np.unique(case)) != set(range(n_cases)):
        _fail(src, "case", f"must number the cases 0..C-1 without gaps, got {sorted(set(case.tolist()))}")
    time = arr[case == 0, header.index("time")]
    per_case = []
    for c in range(n_cases):
        sel = arr[case == c]
        if sel.shape[0] != time.size or not np.allclose(sel[:, header.index("time")], time):
            _fail(src, "time", f"of case {c} differ from those of case 0 (every case needs the same times)")
        per_case.append(sel[:, data_cols])
    values = np.stack(per_case)  # (C, T, cols)
    cols = [header[i] for i in data_cols]
    if quantity == "joint_angles":
        return _corridor(TargetTable(time, tuple(cols), values, quantity, src))
    bodies: list[str] = []
    for name in cols:
        body, _, axis = name.rpartition(".")
        if axis not in AXES or not body:
            _fail(src, name, "must be BODY.x, BODY.y or BODY.z for body positions")
        if body not in bodies:
            bodies.append(body)
    out = np.empty((n_cases, time.size, len(bodies), 3))
    for bi, body in enumerate(bodies):
        for ai, axis in enumerate(AXES):
            name = f"{body}.{axis}"
            if name not in cols:
                _fail(src, name, "column is missing (each body needs .x, .y and .z)")
            out[:, :, bi, ai] = values[:, :, cols.index(name)]
    return TargetTable(time, tuple(bodies), out, quantity, src)


def _corridor(table: TargetTable) -> TargetTable:
    """A table whose columns come as ``NAME`` and ``NAME.sd`` pairs becomes a corridor (mean and
    standard deviation over subjects); a table without ``.sd`` columns is left as it is."""
    sds = [n for n in table.names if n.endswith(SD_SUFFIX)]
    if not sds:
        return table
    means = [n for n in table.names if not n.endswith(SD_SUFFIX)]
    for n in means:
        if n + SD_SUFFIX not in table.names:
            _fail(table.source, n + SD_SUFFIX, "column is missing (a corridor gives every mean column its .sd)")
    for n in sds:
        if n[: -len(SD_SUFFIX)] not in means:
            _fail(table.source, n, "has no mean column")
    take = lambda names: table.values[..., [table.names.index(n) for n in names]]
    return dataclasses.replace(table, names=tuple(means), values=take(means), sd=take([n + SD_SUFFIX for n in means]))


def _read_bvh(path, quantity: str, time_offset: float) -> TargetTable:
    """A recorded trial as BVH: every non-root rotation channel as joint angles (radians,
    unwrapped in time), named like the model's DOFs (``JOINT.Zrotation``). The parsed file rides
    along (``bvh``): :func:`match_trial` checks it against the clip and keeps the simulated DOFs."""
    from neuromotor.model.bvh import read_bvh

    src = str(path)
    if quantity != "joint_angles":
        raise ConfigError(f'{src}: a BVH target gives joint angles; use kind = "joint_angles"')
    clip = read_bvh(path, units=1.0)  # file units: compared with the clip's own in match_trial
    names, cols = [], []
    for j in clip.joints[1:]:
        for axis, col in zip(j.rotation_order, j.rotation_columns):
            names.append(f"{j.name}.{axis}rotation")
            cols.append(col)
    if not names:
        raise ConfigError(f"{src}: the BVH has no joint rotation channels below its root")
    values = np.unwrap(np.deg2rad(clip.motion[:, cols]), axis=0)
    time = time_offset + clip.frame_time * np.arange(clip.motion.shape[0])
    return TargetTable(time, tuple(names), values[None], quantity, src, radians=True, bvh=clip)


# A trial's lengths may differ from the clip's by rounding and by a re-solved skeleton (bone by
# bone); all of them by one factor beyond this is another length unit.
UNIT_RTOL = 0.02
# Frame time and step are commensurate when their ratio is this close to a whole number (BVH
# headers hold 6-7 digits: 0.0333333 s is 4 steps of 1/120 s to 1e-6).
FRAME_RATIO_TOL = 1e-4


def match_trial(table: TargetTable, character, h: float) -> TargetTable:
    """A BVH trial (from :func:`read_target`) on the model of ``character``: one column per
    simulated DOF, in the clip's own Euler orders and on the mocap's angle branch.

    Refused (:class:`ConfigError`, one line naming the file): a skeleton other than the clip's
    (joint names, parents), a joint of a simulated DOF without rotation channels, lengths in
    another unit, a frame time that is neither a whole number of simulation steps ``h`` nor a
    whole fraction of one. Channels of joints the model does not simulate (toes, fingers, face,
    end effectors following the capture), the root's and a virtual root's are left out and
    counted in ``not_fitted``. A joint whose Euler order differs from the clip's is read as the
    same rotation and decomposed in the clip's order, so residuals compare joint rotations, not
    raw Euler numbers of two conventions."""
    from neuromotor.rotations import euler_to_matrix, matrix_to_euler

    trial, clip, model = table.bvh, character.source, character.model
    src = table.source
    if trial is None:
        return table
    where = f"{src}: not the skeleton of the clip {clip.path}"
    parents = lambda c: {j.name: (c.joints[j.parent].name if j.parent >= 0 else None) for j in c.joints}
    a, b = parents(trial), parents(clip)
    missing, extra = [n for n in b if n not in a], [n for n in a if n not in b]
    moved = [f"{n} (parent {a[n]} in the trial, {b[n]} in the clip)" for n in b if n in a and a[n] != b[n]]
    if missing or extra or moved:
        parts = (
            ([f"joints missing {missing[:4]}"] if missing else [])
            + ([f"joints not in the clip {extra[:4]}"] if extra else [])
            + moved[:2]
        )
        raise ConfigError(f"{where}: {'; '.join(parts)}")
    # Units: the median ratio of bone lengths, file units of both.
    tj = {j.name: j for j in trial.joints}
    ratios = []
    for j in clip.joints:
        ref = np.linalg.norm(j.offset) / clip.length_scale
        if ref > 0:
            ratios.append(np.linalg.norm(tj[j.name].offset) / ref)
    ratio = float(np.median(ratios)) if ratios else 1.0
    if not abs(ratio - 1.0) <= UNIT_RTOL:
        raise ConfigError(f"{where}: its lengths are {ratio:.4g} times the clip's (another length unit?)")
    ft = trial.frame_time
    k = ft / h if ft >= h else h / ft
    if abs(k - round(k)) > FRAME_RATIO_TOL * k:
        raise ConfigError(
            f"{src}: frame time {ft:.7g} s and the simulation step h = {h:.7g} s are not "
            f"multiples of one another; set [sim] h to the trial's frame time or a whole fraction of it"
        )
    # Reference branch: the clip's own (unwrapped) angles at the trial's frames.
    ref_motion = np.unwrap(np.deg2rad(np.asarray(clip.motion)), axis=0)
    clip_t = clip.frame_time * np.arange(clip.n_frames)

    def ref_at(cols):
        return np.stack([np.interp(table.time, clip_t, ref_motion[:, c]) for c in cols], -1)

    dof_joints = list(dict.fromkeys(n.rsplit(".", 1)[0] for n in model.dof_names))
    per_joint, reordered = {}, []
    for name in dof_joints:
        cj, t = clip.joints[clip.joint_index(name)], tj[name]
        if not t.rotation_order:
            raise ConfigError(
                f"{where}: joint {name} has no rotation channels in the trial (simulated DOFs {cj.rotation_order})"
            )
        raw = np.deg2rad(np.asarray(trial.motion)[:, list(t.rotation_columns)])
        ref = ref_at(cj.rotation_columns)
        if t.rotation_order == cj.rotation_order:
            ang = np.unwrap(raw, axis=0)
            ang = ang - 2 * np.pi * np.round((ang[0] - ref[0]) / (2 * np.pi))
        elif len(t.rotation_order) == 3 and len(cj.rotation_order) == 3:
            reordered.append(f"{name} {t.rotation_order}->{cj.rotation_order}")
            rot = np.asarray(euler_to_matrix(raw, t.rotation_order))
            ang = np.unwrap(np.asarray(matrix_to_euler(rot, cj.rotation_order, ref)), axis=0)  # type: ignore[arg-type]  # numpy in: jnp converts it
        else:
            raise ConfigError(
                f"{where}: joint {name} rotates by {t.rotation_order} in the trial, {cj.rotation_order} in the clip"
            )
        per_joint[name] = dict(zip(cj.rotation_order, ang.T))
    names = tuple(model.dof_names)
    values = np.stack([per_joint[n.rsplit(".", 1)[0]][n.rsplit(".", 1)[1][0]] for n in names], -1)
    simulated = set(dof_joints)
    left = [j for j in trial.joints[1:] if j.name not in simulated and j.rotation_order]
    n_left = sum(len(j.channels) for j in left)
    note, converted = "", ""
    if left:
        note = (
            f"not fitted: {n_left} channel(s) of {len(left)} joint(s) the model does not simulate "
            f"({', '.join(j.name for j in left[:4])}{', ...' if len(left) > 4 else ''})"
        )
    if reordered:
        more = f" (and {len(reordered) - 3} more)" if len(reordered) > 3 else ""
        converted = f"Euler orders converted (trial->clip): {', '.join(reordered[:3])}{more}"
    return dataclasses.replace(table, names=names, values=values[None], bvh=None, not_fitted=note, converted=converted)


def window_indices(sim_time: np.ndarray, window, source: str, field: str) -> tuple[int, int]:
    """[i0, i1) of the simulation samples inside ``window = (t0, t1)`` (clip seconds)."""
    t0, t1 = float(window[0]), float(window[1])
    tol = 1e-9
    if not t1 > t0:
        _fail(source, field, f"must be [t0, t1] with t1 > t0, got {list(window)}")
    if t0 < sim_time[0] - tol or t1 > sim_time[-1] + tol:
        _fail(source, field, f"{list(window)} is outside the simulated span [{sim_time[0]:.4f}, {sim_time[-1]:.4f}] s")
    inside = np.nonzero((sim_time >= t0 - tol) & (sim_time <= t1 + tol))[0]
    if inside.size < 2:
        _fail(source, field, f"{list(window)} holds fewer than 2 simulation samples")
    return int(inside[0]), int(inside[-1]) + 1


def resample(table: TargetTable, times: np.ndarray, field: str = "window") -> np.ndarray:
    """Linear interpolation of every column onto ``times`` (which must lie inside the file)."""
    tol = 1e-9
    if times[0] < table.time[0] - tol or times[-1] > table.time[-1] + tol:
        _fail(
            table.source,
            field,
            f"[{times[0]:.4f}, {times[-1]:.4f}] s is outside the target's time "
            f"span [{table.time[0]:.4f}, {table.time[-1]:.4f}] s",
        )
    flat = table.values.reshape(table.values.shape[0], table.time.size, -1)
    out = np.stack([[np.interp(times, table.time, col) for col in case.T] for case in flat])  # (C, k', T)
    out = np.swapaxes(out, 1, 2)
    return out.reshape((table.values.shape[0], times.size) + table.values.shape[2:])


def write_target_csv(path, time, names, values, quantity="joint_angles", header_comment=None):
    """Write a trajectory target in the CSV layout (temp file then rename)."""

    path = pathlib.Path(path)
    values = np.asarray(values)
    if quantity == "joint_angles":
        cols = list(names)
        flat = values
    else:
        cols = [f"{n}.{a}" for n in names for a in AXES]
        flat = values.reshape(values.shape[0], values.shape[1], -1)
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        if header_comment:
            for line in header_comment.splitlines():
                fh.write(f"# {line}\n")
        w = csv.writer(fh)
        w.writerow(["case", "time"] + cols)
        for c in range(flat.shape[0]):
            for i, t in enumerate(time):
                w.writerow([c, repr(float(t))] + [f"{float(v):.10g}" for v in flat[c, i]])
    return path


# ----------------------------------------------------------------------------- body targets


@dataclasses.dataclass
class Series:
    """One case's series of a body target: file time in seconds (from the file's time 0), the
    values and, for a corridor, their standard deviation (file units)."""

    time: np.ndarray  # (T,) s
    value: np.ndarray  # (T,)
    sd: np.ndarray | None
    source: str  # the file
    column: str
    lines: np.ndarray  # (T,) the file's line of each sample


def _series_rows(path: pathlib.Path) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """Header and (line number, cells) of every data row; ``#`` lines and blank lines skipped."""
    src = str(path)
    if not path.exists():
        raise ConfigError(f"{src}: target file not found")
    if path.suffix.lower() != ".csv":
        raise ConfigError(f"{src}: a body target must be a .csv file, got {path.suffix!r}")
    rows = []
    with open(path, newline="", encoding="utf-8") as fh:
        reader = csv.reader(fh)
        for r in reader:
            if r and any(x.strip() for x in r) and not r[0].lstrip().startswith("#"):
                rows.append((reader.line_num, [x.strip() for x in r]))
    if not rows:
        raise ConfigError(f"{src}: empty CSV target")
    return rows[0][1], rows[1:]


def _read_series_file(path: pathlib.Path, time_unit: str, column: str | None) -> list[Series]:
    """Every case of one file (a ``case`` column numbers them; without it, one case)."""
    src = str(path)
    header, data = _series_rows(path)
    if "time" not in header:
        _fail(src, "time", f"column is missing (header: {header})")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise ConfigError(f"{src}: column {dup[0]!r} appears twice in the header")
    if not data:
        raise ConfigError(f"{src}: CSV target has a header but no rows")
    means = [h for h in header if h not in ("time", "case") and not h.endswith(SD_SUFFIX)]
    for h in header:
        if h.endswith(SD_SUFFIX) and h[: -len(SD_SUFFIX)] not in means:
            _fail(src, h, "has no mean column")
    if column is not None:
        if column not in means:
            raise ConfigError(f"{src}: column {column!r} (fit.target.column) is missing; data columns: {means}")
    elif len(means) != 1:
        raise ConfigError(
            f"{src}: has {len(means)} data columns {means}; name the one to fit with fit.target.column"
            if means
            else f"{src}: has no data column besides time and case"
        )
    name = column or means[0]
    cols = {"time": header.index("time"), "value": header.index(name)}
    if name + SD_SUFFIX in header:
        cols["sd"] = header.index(name + SD_SUFFIX)
    if "case" in header:
        cols["case"] = header.index("case")
    shown = {"time": "time", "value": name, "sd": name + SD_SUFFIX, "case": "case"}
    parsed: dict[int, list] = {}
    for line, cells in data:
        if len(cells) != len(header):
            raise ConfigError(f"{src}: line {line} has {len(cells)} columns, the header has {len(header)}")
        row = {}
        for key, i in cols.items():
            try:
                row[key] = float(cells[i])
            except ValueError:
                raise ConfigError(f"{src}: line {line}: field '{shown[key]}' is not a number: {cells[i]!r}") from None
            if not np.isfinite(row[key]):
                raise ConfigError(f"{src}: line {line}: field '{shown[key]}' is not finite: {cells[i]!r}")
        if "sd" in row and not row["sd"] > 0:
            raise ConfigError(f"{src}: line {line}: field '{shown['sd']}' must be > 0, got {cells[cols['sd']]!r}")
        case = row.get("case", 0.0)
        if case != int(case) or case < 0:
            raise ConfigError(
                f"{src}: line {line}: field 'case' must be a case number 0, 1, ..., got {cells[cols['case']]!r}"
            )
        parsed.setdefault(int(case), []).append((line, row))
    n = max(parsed) + 1
    if len(parsed) != n:
        _fail(src, "case", f"must number the cases 0..C-1 without gaps, got {sorted(parsed)}")
    scale = TIME_UNITS[time_unit]
    out = []
    for c in range(n):
        rows = parsed[c]
        for (_, prev), (line, row) in zip(rows, rows[1:]):
            if not row["time"] > prev["time"]:
                raise ConfigError(
                    f"{src}: line {line}: field 'time' = {row['time']:g} is not after the previous "
                    f"{prev['time']:g} (times must increase{' within each case' if n > 1 else ''})"
                )
        if len(rows) < 2:
            _fail(src, "time", f"has {len(rows)} sample(s){f' in case {c}' if n > 1 else ''}; at least 2 are needed")
        arr = lambda key: np.array([r[key] for _, r in rows])
        sd = arr("sd") if "sd" in cols else None
        lines = np.array([ln for ln, _ in rows])
        out.append(Series(scale * arr("time"), arr("value"), sd, src, name, lines))
    return out


def read_series(paths, time_unit: str, column: str | None = None, n_cases: int | None = None) -> list[Series]:
    """One :class:`Series` per case of a body target: from one file (a ``case`` column numbers
    the cases; layout in the module docstring) or one file per case. ``time_unit``: ``s`` or
    ``ms``. Refused (:class:`ConfigError` naming the file, and the line where it applies): a
    missing or non-increasing time column, a non-numeric or non-finite entry, an sd <= 0, a
    ``.sd`` column without its mean, several data columns and no ``column``, a case count other
    than ``n_cases``, and files of one target of which some are corridors and some are not."""
    paths = [pathlib.Path(p) for p in paths]
    if time_unit not in TIME_UNITS:
        raise ConfigError(f"{paths[0]}: unknown time unit {time_unit!r}; use one of {list(TIME_UNITS)}")
    if len(paths) == 1:
        series = _read_series_file(paths[0], time_unit, column)
        if n_cases is not None and len(series) != n_cases:
            raise ConfigError(
                f"{paths[0]}: holds {len(series)} case(s) but there are {n_cases} [[perturbation]] entries "
                f"(one series per case: a 'case' column numbering them from 0, or files = [...] one per case)"
            )
    else:
        series = []
        for p in paths:
            got = _read_series_file(p, time_unit, column)
            if len(got) != 1:
                raise ConfigError(f"{p}: holds {len(got)} cases; each of files = [...] gives one case")
            series += got
    corridor = [s for s in series if s.sd is not None]
    if corridor and len(corridor) != len(series):
        bad = next(s for s in series if s.sd is None)
        raise ConfigError(
            f"{bad.source}: field '{bad.column}{SD_SUFFIX}' column is missing but {corridor[0].source} has one "
            f"(a target's cases are all corridors, mean and {SD_SUFFIX}, or all single trials)"
        )
    return series


def write_series_csv(
    path, time, value, sd=None, name: str = "value", time_unit: str = "s", header_comment: str | None = None
) -> pathlib.Path:
    """Write a body target (:func:`read_series` layout): ``time`` (T,) in seconds (written in
    ``time_unit``), ``value`` (T,) or (C, T) (then with a ``case`` column) and optionally its
    ``sd`` (same shape: a corridor), in the units the config will declare (temp file then rename)."""
    path = pathlib.Path(path)
    value = np.asarray(value, float)
    cases = value.ndim == 2
    value = value if cases else value[None]
    sd_arr = None if sd is None else np.broadcast_to(np.asarray(sd, float), value.shape)
    t = np.asarray(time, float) / TIME_UNITS[time_unit]
    with atomic_path(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        for line in (header_comment or "").splitlines():
            fh.write(f"# {line}\n")
        w = csv.writer(fh)
        w.writerow((["case"] if cases else []) + ["time", name] + ([name + SD_SUFFIX] if sd_arr is not None else []))
        for c in range(value.shape[0]):
            for i, ti in enumerate(t):
                row = ([c] if cases else []) + [repr(float(ti)), f"{float(value[c, i]):.12g}"]
                w.writerow(row + ([f"{float(sd_arr[c, i]):.12g}"] if sd_arr is not None else []))
    return path
