"""The CLI's persistent compilation cache (issue 16, item 4): where it lives, how it is turned
off, that an already given JAX cache folder is respected and that importing the package does
not turn it on."""

import os
import pathlib
import subprocess
import sys

import pytest

from neuromotor import compiler

PROBE = """
import sys, jax, jax.numpy as jnp
import neuromotor
print("import:", jax.config.jax_compilation_cache_dir)
if sys.argv[1] == "enable":
    from neuromotor.compiler import enable_compile_cache
    print("enabled:", enable_compile_cache())
    jax.jit(lambda x: jnp.sin(x) * 2.0 + 1.0)(jnp.ones(7)).block_until_ready()
"""


def _probe(tmp_path, mode, **env):
    clean = {k: v for k, v in os.environ.items()
             if k not in ("JAX_COMPILATION_CACHE_DIR", "NEUROMOTOR_CACHE_DIR", "XDG_CACHE_HOME",
                          "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")}
    clean.update(HOME=str(tmp_path / "home"), **env)
    out = subprocess.run([sys.executable, "-c", PROBE, mode], env=clean, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    return dict(line.split(": ", 1) for line in out.stdout.strip().splitlines())


def test_cache_dir_rules(monkeypatch, tmp_path):
    monkeypatch.delenv("NEUROMOTOR_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compiler.cache_dir() == tmp_path / "xdg" / "neuromotor" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compiler.cache_dir() == tmp_path / "home" / ".cache" / "neuromotor" / "jax"
    monkeypatch.setenv("NEUROMOTOR_CACHE_DIR", str(tmp_path / "mine"))
    assert compiler.cache_dir() == tmp_path / "mine"
    for off in ("off", "OFF", "0", ""):
        monkeypatch.setenv("NEUROMOTOR_CACHE_DIR", off)
        assert compiler.cache_dir() is None
        assert compiler.enable_compile_cache() is None


def test_import_does_not_enable_and_cli_helper_fills_the_folder(tmp_path):
    got = _probe(tmp_path, "enable", NEUROMOTOR_CACHE_DIR=str(tmp_path / "c"))
    assert got["import"] == "None"  # `import neuromotor` leaves JAX's cache alone
    assert got["enabled"] == str(tmp_path / "c")
    assert any((tmp_path / "c").iterdir())  # the program was written to the cache


def test_xdg_default_and_respect_for_jax_variable(tmp_path):
    got = _probe(tmp_path, "enable", XDG_CACHE_HOME=str(tmp_path / "xdg"))
    assert got["enabled"] == str(tmp_path / "xdg" / "neuromotor" / "jax")
    assert any((tmp_path / "xdg" / "neuromotor" / "jax").iterdir())
    theirs = tmp_path / "theirs"
    got = _probe(tmp_path, "enable", JAX_COMPILATION_CACHE_DIR=str(theirs),
                 NEUROMOTOR_CACHE_DIR=str(tmp_path / "ignored"))
    assert got["enabled"] == str(theirs) and not (tmp_path / "ignored").exists()
    got = _probe(tmp_path, "enable", NEUROMOTOR_CACHE_DIR="off", XDG_CACHE_HOME=str(tmp_path / "x2"))
    assert got["enabled"] == "None" and not (tmp_path / "x2").exists()


def test_unwritable_folder_leaves_the_cache_off(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    got = _probe(tmp_path, "enable", NEUROMOTOR_CACHE_DIR=str(blocker / "sub"))
    assert got["enabled"] == "None"  # compiles as before, no error
