"""Data safety of the command line (issue 16): outputs are checked before any computation, never
overwrite an input, failures are one line naming the file or field with exit status 2, and no
temporary file outlives its process (signals clean up; SIGKILL leftovers are swept later)."""

from __future__ import annotations

import errno
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import textwrap
import time

import numpy as np
import pytest

from neuromotor import atomic
from neuromotor.io import outputs

from neuromotor import cli
from neuromotor.cli import main
from neuromotor.config import ConfigError, simulation_config
from neuromotor.studies.simulate import default_clip_path

REPO = pathlib.Path(__file__).resolve().parents[2]
HIT = """
[[perturbation]]
body = "chest"
direction = [0.0, 0.0, 1.0]
magnitude = 400.0
start = {start}
duration = 0.1
"""


def snapshot(folder: pathlib.Path) -> dict[str, bytes | None]:
    """Every entry under ``folder`` (hidden ones too) with its bytes (None for a folder)."""
    return {str(p.relative_to(folder)): (None if p.is_dir() else p.read_bytes()) for p in sorted(folder.rglob("*"))}


def one_line_error(capsys, *names) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    assert "Traceback" not in err and err.startswith("neuromotor ") and ": error: " in err, err
    for name in names:
        assert str(name) in err, (name, err)
    return err


@pytest.fixture
def no_computation(monkeypatch):
    """The commands' bodies fail the test if reached: the pre-flight must stop them first."""
    def boom(args):
        raise AssertionError(f"{args.command} started computing before its outputs were checked")

    for name in ("cmd_idyn", "cmd_simulate", "cmd_render", "cmd_plot", "cmd_sweep", "cmd_fit", "cmd_export_bvh",
                 "cmd_export_mjcf", "cmd_demo", "cmd_bench"):
        monkeypatch.setattr(cli, name, boom)


@pytest.fixture
def clip(tmp_path) -> pathlib.Path:
    path = tmp_path / "clip.bvh"
    path.write_bytes(default_clip_path().read_bytes())
    return path


def fake_run(path: pathlib.Path, source_clip) -> pathlib.Path:
    np.savez(path, time=np.zeros(2), theta=np.zeros((2, 1)), dof_names=np.array(["a"]),
             source_clip=np.asarray(str(source_clip)), source_units=np.asarray("1.0"), up_axis=np.asarray(1))
    return path


# ----------------------------------------------------------------------- an output is an input

def test_simulate_onto_its_own_config_is_refused(tmp_path, capsys, no_computation):
    cfg = tmp_path / "X.toml"
    cfg.write_text(HIT.format(start=1.0))
    before = snapshot(tmp_path)
    assert main(["simulate", str(cfg), "-o", str(cfg)]) == 2
    one_line_error(capsys, cfg, "input")
    assert snapshot(tmp_path) == before


def test_simulate_onto_the_configs_clip_is_refused(tmp_path, clip, capsys, no_computation):
    cfg = tmp_path / "X.toml"
    cfg.write_text('clip = "clip.bvh"\n' + HIT.format(start=1.0))
    before = snapshot(tmp_path)
    other = tmp_path / "." / "clip.bvh"  # another spelling of the same file
    assert main(["simulate", str(cfg), "-o", str(other)]) == 2
    one_line_error(capsys, "clip.bvh", "input")
    assert snapshot(tmp_path) == before


def test_export_bvh_onto_its_run_or_the_runs_clip_is_refused(tmp_path, clip, capsys, no_computation):
    run = fake_run(tmp_path / "run.npz", clip)
    before = snapshot(tmp_path)
    assert main(["export-bvh", str(run), "-o", str(run)]) == 2
    one_line_error(capsys, run)
    assert main(["export-bvh", str(run), "-o", str(clip)]) == 2  # would replace the source clip
    one_line_error(capsys, clip)
    assert snapshot(tmp_path) == before


def test_export_mjcf_onto_its_clip_is_refused(tmp_path, clip, capsys, no_computation):
    before = snapshot(tmp_path)
    hard = tmp_path / "hard.bvh"
    os.link(clip, hard)  # the same file under another name
    assert main(["export-mjcf", str(clip), "-o", str(hard)]) == 2
    one_line_error(capsys, hard)
    os.unlink(hard)
    assert main(["export-mjcf", str(clip), "-o", str(clip)]) == 2
    one_line_error(capsys, clip)
    assert snapshot(tmp_path) == before


def test_render_plot_idyn_onto_their_input_are_refused(tmp_path, clip, capsys, no_computation):
    run = fake_run(tmp_path / "run.npz", clip)
    before = snapshot(tmp_path)
    for argv in (["render", str(run), "-o", str(run)], ["plot", str(run), "-o", str(run)],
                 ["idyn", str(clip), "-o", str(clip)]):
        assert main(argv) == 2, argv
        one_line_error(capsys, argv[1])
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------- outputs that cannot be written

def test_output_under_a_regular_file(tmp_path, clip, capsys, no_computation):
    notes = tmp_path / "notes.txt"
    notes.write_text("keep me\n")
    before = snapshot(tmp_path)
    for argv in (["idyn", str(clip), "-o", str(notes / "x.npz")],
                 ["export-mjcf", str(clip), "-o", str(notes / "sub" / "x.xml")],
                 ["demo", "-o", str(notes / "demo")]):
        assert main(argv) == 2, argv
        one_line_error(capsys, notes, "not a directory")
    assert snapshot(tmp_path) == before


def test_output_at_an_existing_directory(tmp_path, clip, capsys, no_computation):
    (tmp_path / "out.npz").mkdir()
    before = snapshot(tmp_path)
    assert main(["idyn", str(clip), "-o", str(tmp_path / "out.npz")]) == 2
    one_line_error(capsys, tmp_path / "out.npz", "is a directory")
    assert main(["export-mjcf", str(clip), "-o", str(tmp_path)]) == 2
    one_line_error(capsys, tmp_path, "is a directory")
    assert snapshot(tmp_path) == before


def test_output_folder_that_is_a_file(tmp_path, capsys, no_computation):
    cfg = tmp_path / "sweep.toml"
    cfg.write_text(HIT.format(start=1.0) + "[sweep]\nmagnitudes = [100.0, 200.0]\n")
    taken = tmp_path / "taken"
    taken.write_text("a file, not a folder\n")
    before = snapshot(tmp_path)
    assert main(["sweep", str(cfg), "-o", str(taken)]) == 2
    one_line_error(capsys, taken, "not a directory")
    assert main(["sweep", str(cfg), "-o", str(cfg)]) == 2  # the config itself as the folder
    one_line_error(capsys, cfg)
    assert main(["demo", "-o", str(taken)]) == 2
    one_line_error(capsys, taken)
    assert snapshot(tmp_path) == before


def test_device_file_as_output_is_refused(tmp_path, clip, capsys, no_computation):
    assert main(["export-mjcf", str(clip), "-o", os.devnull]) == 2  # a rename would replace /dev/null
    one_line_error(capsys, os.devnull, "regular file")
    assert os.path.exists(os.devnull) and not os.path.isfile(os.devnull)


def test_missing_parent_folders_are_still_fine(tmp_path, clip, capsys, monkeypatch):
    """`-o new/sub/model.xml` keeps working: the writer creates the folders."""
    out = tmp_path / "new" / "sub" / "model.xml"
    assert main(["export-mjcf", str(clip), "-o", str(out)]) == 0
    assert out.read_text().startswith("<mujoco")
    assert [p.name for p in out.parent.iterdir()] == ["model.xml"]


@pytest.mark.parametrize("err", [errno.EROFS, errno.EACCES])
def test_unwritable_folder_is_found_before_computing(tmp_path, clip, capsys, no_computation, monkeypatch, err):
    """Simulated: the probe file cannot be created (a read-only file system or no permission).
    The real thing, without root, is in the next test."""
    real = tempfile.mkstemp

    def refuse(*a, dir=None, **k):
        if dir is not None and pathlib.Path(dir).resolve() == (tmp_path / "ro").resolve():
            raise OSError(err, os.strerror(err), os.path.join(dir, ".probe.tmp"))
        return real(*a, dir=dir, **k)

    (tmp_path / "ro").mkdir()
    monkeypatch.setattr(outputs.tempfile, "mkstemp", refuse)
    target = tmp_path / "ro" / "id.npz"
    assert main(["idyn", str(clip), "-o", str(target)]) == 2
    err_line = one_line_error(capsys, target, os.strerror(err))
    assert ".probe" not in err_line and ".tmp" not in err_line  # names the target, not a temporary
    assert main(["demo", "-o", str(tmp_path / "ro" / "demo")]) == 2  # a folder output to be made there
    one_line_error(capsys, tmp_path / "ro" / "demo", os.strerror(err))
    assert list((tmp_path / "ro").iterdir()) == []


def test_no_permission_is_found_before_computing(capsys, no_computation, clip):
    """A folder this user may not write to (as root, the test drops to 'nobody' for the call:
    root writes anywhere)."""
    base = pathlib.Path(tempfile.mkdtemp(prefix="nm-ro-"))
    try:
        os.chmod(base, 0o755)
        ro = base / "ro"
        ro.mkdir()
        os.chmod(ro, 0o555)
        target = ro / "id.npz"
        if os.geteuid() == 0:
            os.seteuid(65534)
        try:
            if os.access(ro, os.W_OK, effective_ids=os.access in os.supports_effective_ids):
                pytest.skip("cannot make a folder unwritable here")
            status = main(["idyn", str(clip), "-o", str(target)])
        finally:
            if os.getuid() == 0:
                os.seteuid(0)
        assert status == 2
        one_line_error(capsys, target, "Permission denied")
        assert list(ro.iterdir()) == []
    finally:
        os.chmod(base / "ro", 0o755)
        for p in sorted(base.rglob("*"), reverse=True):
            p.rmdir() if p.is_dir() else p.unlink()
        base.rmdir()


def test_atomic_write_errors_name_the_target_not_the_temporary(tmp_path, monkeypatch):
    real = tempfile.mkstemp

    def refuse(*a, **k):
        raise PermissionError(errno.EACCES, "Permission denied", os.path.join(str(tmp_path), ".x.tmp"))

    monkeypatch.setattr(atomic.tempfile, "mkstemp", refuse)
    with pytest.raises(PermissionError) as e:
        with atomic.atomic_path(tmp_path / "x.npz"):
            pass
    assert e.value.filename == str(tmp_path / "x.npz")
    monkeypatch.setattr(atomic.tempfile, "mkstemp", real)
    with pytest.raises(OSError) as e:  # a failure inside the block, on the temporary
        with atomic.atomic_path(tmp_path / "y.npz") as tmp:
            raise OSError(errno.ENOSPC, "No space left on device", str(tmp))
    assert e.value.filename == str(tmp_path / "y.npz") and e.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


def test_a_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "x.csv"
    target.write_text("old\n")
    os.chmod(target, 0o640)
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("late failure")
    assert target.read_text() == "old\n" and [p.name for p in tmp_path.iterdir()] == ["x.csv"]
    with atomic.atomic_path(target) as tmp:
        tmp.write_text("new\n")
    assert target.read_text() == "new\n" and (target.stat().st_mode & 0o777) == 0o640  # mode kept


# ----------------------------------------------------------------------- configs

def test_empty_config_names_the_file(tmp_path, capsys):
    for name, data in (("empty.toml", b""), ("blank.toml", b"  \n\t\n"), ("comments.toml", b"# nothing\n")):
        cfg = tmp_path / name
        cfg.write_bytes(data)
        out = tmp_path / "run.npz"
        assert main(["simulate", str(cfg), "-o", str(out)]) == 2
        one_line_error(capsys, cfg)
        assert not out.exists()


def test_binary_config_names_the_file(tmp_path, capsys):
    for name, data in (("bin.toml", bytes(range(256)) * 4), ("nul.toml", b"a = 1\n\x00\x00\n")):
        cfg = tmp_path / name
        cfg.write_bytes(data)
        assert main(["simulate", str(cfg), "-o", str(tmp_path / "run.npz")]) == 2
        one_line_error(capsys, cfg, "not a text")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bin.toml", "nul.toml"]


@pytest.mark.parametrize("start, duration, expect", [
    (200.0, None, "after the end"),   # the embedded clip ends at 15.1 s
    (2.5, 1.0, "after the end"),      # after the simulated window [0, 1)
    (0.2, 1.0, "over before"),        # before the window [1, 2): never acts
])
def test_perturbation_outside_the_simulated_window(tmp_path, capsys, start, duration, expect):
    cfg = tmp_path / "late.toml"
    sim = "" if duration is None else f"[sim]\nstart = {1.0 if expect == 'over before' else 0.0}\nduration = {duration}\n"
    cfg.write_text(sim + HIT.format(start=start))
    before = snapshot(tmp_path)
    assert main(["simulate", str(cfg), "-o", str(tmp_path / "run.npz")]) == 2
    one_line_error(capsys, cfg, "perturbation[0].start", expect)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("flag, value", [("--ks", "-400"), ("--ks", "nan"), ("--kd", "-1"), ("--kd", "inf")])
def test_bad_gain_on_the_command_line(tmp_path, capsys, flag, value):
    with pytest.raises(SystemExit) as e:
        main(["simulate", "-o", str(tmp_path / "run.npz"), flag, value])
    assert e.value.code == 2
    one_line_error(capsys, flag, value)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("value", ["-400", "nan", "inf"])
def test_bad_gain_in_a_config(value):
    with pytest.raises(ConfigError, match=r"f\.toml: field 'gains\.ks'"):
        simulation_config({"gains": {"ks": float(value)}}, "f.toml")


@pytest.mark.parametrize("value", ["0", "nan", "-0.01", "inf"])
def test_bad_mjcf_timestep(tmp_path, clip, capsys, value):
    out = tmp_path / "model.xml"
    with pytest.raises(SystemExit) as e:
        main(["export-mjcf", str(clip), "-o", str(out), "--timestep", value])
    assert e.value.code == 2
    one_line_error(capsys, "--timestep", value)
    assert not out.exists()


def test_mjcf_function_checks_the_timestep(tmp_path):
    from neuromotor.io.mjcf import export_mjcf
    from neuromotor.studies.simulate import load_character

    character, _ = load_character(None)
    for bad in (0.0, float("nan"), -1.0):
        with pytest.raises(ValueError, match="timestep"):
            export_mjcf(character, tmp_path / "m.xml", timestep=bad)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------- temporaries and signals

# argv[3]: "default" gives SIGINT Python's own handler (a terminal's Ctrl-C: a test worker may
# hand down an ignored SIGINT, as a shell does to a background job), "ignore" ignores it.
SLOW_WRITER = textwrap.dedent("""
    import faulthandler, pathlib, signal, sys, time
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # the stacks, should it not exit
    signal.signal(signal.SIGINT, signal.default_int_handler if sys.argv[3] == "default" else signal.SIG_IGN)
    real = pathlib.Path.write_text
    def slow(self, text, *a, **k):  # the model XML: write half, then hang
        real(self, text[:100], *a, **k)
        print("WRITING", flush=True)
        time.sleep(120)
    pathlib.Path.write_text = slow
    from neuromotor.cli import main
    sys.exit(main(["export-mjcf", sys.argv[1], "-o", sys.argv[2]]))
""")


def _start_slow_export(clip, out, sigint: str = "default") -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", SLOW_WRITER, str(clip), str(out), sigint], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO)
    line = proc.stdout.readline()  # the temporary exists and is half written
    assert line.strip() == "WRITING", proc.stderr.read()
    temps = [p for p in out.parent.iterdir() if atomic.is_temporary(p.name)]
    assert len(temps) == 1 and temps[0].name.startswith(".model.xml.neuromotor-")
    return proc


def _exit_status(proc: subprocess.Popen, timeout: float = 60.0) -> int:
    """The child's exit status; a child that does not exit fails the test with its threads' stacks."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(2.0)
        proc.kill()
        _, err = proc.communicate(timeout=30)
        pytest.fail(f"the interrupted export did not exit within {timeout:g} s; its stderr:\n{err[-6000:]}")


@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, -signal.SIGTERM), (signal.SIGINT, 130)])
def test_signal_removes_the_temporary(tmp_path, clip, sig, status):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    proc = _start_slow_export(clip, out_dir / "model.xml")
    proc.send_signal(sig)
    assert _exit_status(proc) == status
    err = proc.stderr.read()
    assert "Traceback" not in err
    assert list(out_dir.iterdir()) == []  # no target, no temporary


def test_an_ignored_sigint_leaves_the_write_going(tmp_path, clip):
    """A process that ignores SIGINT (a background job) goes on writing: its temporary stays; a
    SIGTERM then still removes it."""
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    proc = _start_slow_export(clip, out_dir / "model.xml", sigint="ignore")
    proc.send_signal(signal.SIGINT)
    time.sleep(1.0)
    assert proc.poll() is None
    left = [p.name for p in out_dir.iterdir()]
    assert len(left) == 1 and atomic.is_temporary(left[0])
    proc.send_signal(signal.SIGTERM)
    assert _exit_status(proc) == -signal.SIGTERM
    assert list(out_dir.iterdir()) == []


def test_sigkill_leftover_is_swept_by_the_next_write(tmp_path, clip):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    proc = _start_slow_export(clip, out_dir / "model.xml")
    proc.kill()
    proc.wait(timeout=60)
    left = [p.name for p in out_dir.iterdir()]
    assert len(left) == 1 and atomic.is_temporary(left[0])  # SIGKILL cannot be caught ...
    with atomic.atomic_path(out_dir / "other.csv") as tmp:  # ... the next write there removes it
        tmp.write_text("x\n")
    assert [p.name for p in out_dir.iterdir()] == ["other.csv"]


def test_stale_sweep_spares_live_and_foreign_files(tmp_path):
    live_pid = os.getppid()  # alive and not us
    fresh = tmp_path / f".a.npz.neuromotor-{live_pid}-abcd1234.tmp.npz"
    old = tmp_path / f".b.npz.neuromotor-{live_pid}-abcd1234.tmp.npz"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    orphan = tmp_path / f".c.png.neuromotor-{dead.pid}-zz_9zz99.tmp.png"
    foreign = [tmp_path / ".c.png-abcd1234.png", tmp_path / ".neuromotor-notes.tmp", tmp_path / "keep.npz"]
    for p in [fresh, old, orphan, *foreign]:
        p.write_text("x")
    two_hours_ago = time.time() - 7200
    os.utime(old, (two_hours_ago, two_hours_ago))
    removed = atomic.remove_stale_temporaries(tmp_path)
    assert sorted(p.name for p in removed) == sorted([old.name, orphan.name])
    assert fresh.exists() and all(p.exists() for p in foreign)


def test_probe_leaves_nothing(tmp_path, clip):
    outputs.check_outputs(files=[tmp_path / "a" / "b.npz"], folders=[tmp_path / "d"], inputs=[clip])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.bvh"]
