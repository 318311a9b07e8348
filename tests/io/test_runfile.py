"""RUN.npz reader and writer (neuromotor.io.runfile): the field contract and its checks."""

from __future__ import annotations

import re

import numpy as np
import pytest

from neuromotor.errors import UserError
from neuromotor.io.runfile import (DRAW_FIELDS, EXPORT_FIELDS, RunFileError, read_run, read_run_info,
                                   write_run)


def _minimal(T=5) -> dict:
    t = np.arange(T) / 10.0
    return {"time": t, "theta": np.zeros((T, 2)), "dof_names": np.array(["a.Xrotation", "a.Yrotation"]),
            "source_clip": np.asarray("clip.bvh"), "source_units": np.asarray("0.01"), "up_axis": np.asarray(1)}


def test_write_then_read_round_trip(tmp_path):
    arrays = _minimal()
    path = write_run(tmp_path / "run.npz", arrays, extra={"ball_radius_note": np.asarray(1.0)})
    got = read_run(path, EXPORT_FIELDS)
    assert set(got) == set(EXPORT_FIELDS)
    assert np.array_equal(got["time"], arrays["time"])
    assert read_run_info(path)["arrays"]["ball_radius_note"] == []


def test_extra_arrays_may_not_replace_a_field(tmp_path):
    with pytest.raises(ValueError, match="time"):
        write_run(tmp_path / "run.npz", _minimal(), extra={"time": np.zeros(3)})
    assert not (tmp_path / "run.npz").exists()


def test_reader_names_the_missing_field_and_the_file(tmp_path):
    path = write_run(tmp_path / "run.npz", _minimal())
    with pytest.raises(RunFileError, match=r"run\.npz: missing array\(s\) skeleton_points"):
        read_run(path, DRAW_FIELDS)


def test_checks_name_the_field(tmp_path):
    arrays = _minimal()
    arrays["time"] = arrays["time"][::-1].copy()
    path = write_run(tmp_path / "run.npz", arrays)
    with pytest.raises(RunFileError, match="field 'time' must be strictly increasing"):
        read_run(path, EXPORT_FIELDS)


@pytest.mark.parametrize("kind", ["missing", "directory", "text", "not_a_run"])
def test_info_of_a_bad_file_is_a_user_error(tmp_path, kind):
    path = tmp_path / "bad.npz"
    if kind == "directory":
        path.mkdir()
    elif kind == "text":
        path.write_text("hello")
    elif kind == "not_a_run":
        np.savez(path, x=np.zeros(3))
    with pytest.raises(UserError, match="bad.npz"):
        read_run_info(path)


@pytest.mark.parametrize("fields, needle", [
    (dict(assist_force=np.zeros((5, 3))), "field 'assist_point' is missing (assist_force and assist_point come together)"),
    (dict(assist_force=np.zeros((4, 3)), assist_point=np.zeros((5, 3))), "field 'assist_force' must have shape (T=5, 3)"),
    (dict(assist_force=np.full((5, 3), np.nan), assist_point=np.zeros((5, 3))), "field 'assist_force'"),
])
def test_the_assist_fields_come_together_and_are_checked(tmp_path, fields, needle):
    path = write_run(tmp_path / "run.npz", {**_minimal(), **fields})
    with pytest.raises(RunFileError, match=re.escape(needle)):
        read_run(path, EXPORT_FIELDS)
    both = dict(assist_force=np.ones((5, 3)), assist_point=np.zeros((5, 3)))
    got = read_run(write_run(tmp_path / "ok.npz", {**_minimal(), **both}), EXPORT_FIELDS)
    np.testing.assert_array_equal(got["assist_force"], both["assist_force"])
