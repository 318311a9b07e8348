"""The documentation site (mkdocs.yml: the README as front page, the architecture map, the guides
and an API reference generated from the docstrings by mkdocstrings) builds offline with warnings
as errors, and holds what it should."""

from __future__ import annotations

import pathlib
import re
import shutil
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
MKDOCS = [sys.executable, "-m", "mkdocs", "build", "--strict"]


def _build(config: pathlib.Path, site: pathlib.Path) -> subprocess.CompletedProcess:
    return subprocess.run([*MKDOCS, "-f", str(config), "-d", str(site)], capture_output=True, text=True,
                          timeout=300, check=False)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    site = tmp_path_factory.mktemp("site")
    out = _build(ROOT / "mkdocs.yml", site)
    assert out.returncode == 0, out.stderr[-4000:]
    assert "WARNING" not in out.stderr, out.stderr[-4000:]
    return site


def _text(site, page) -> str:
    return (site / page / "index.html" if page else site / "index.html").read_text(encoding="utf-8")


def test_front_page_is_the_readme_with_the_equation_table(site):
    index = _text(site, "")
    assert "Set-up (two commands)" in index and "Where each equation lives" in index
    assert "Eq. 2: linearly implicit step" in index
    assert (site / "images" / "viewer.png").is_file() and 'src="images/viewer.png"' in index
    assert "Trusted networks only" in index
    arch = _text(site, "architecture")
    assert "Which module holds which equation" in arch and "The step (Eq. 2) as named stages" in arch


def test_api_reference_documents_the_public_names(site):
    physics, studies, fit, sweep = (_text(site, f"api/{p}") for p in ("physics", "studies", "fit", "sweep"))
    for name in ("SimModel", "Params", "Data", "simulate", "step", "rollout"):
        assert re.search(rf'id="neuromotor\.physics\.dynamics\.{name}"', physics), name
    for name in ("prepare", "run"):
        assert f'id="neuromotor.studies.simulate.{name}"' in studies, name
    assert 'id="neuromotor.model.load.load_character"' in _text(site, "api/model")
    assert 'id="neuromotor.studies.fit.driver.fit"' in fit and 'id="neuromotor.studies.fit.problem.make_problem"' in fit
    assert 'id="neuromotor.studies.sweep.sweep_from_config"' in sweep
    # A docstring's text made it through (not only the signature).
    assert "lax.scan" in physics and "Generalized velocity layout" in _text(site, "api/model")
    assert ":class:" not in physics and ":func:" not in physics     # Sphinx roles stripped


def test_site_fetches_nothing(site):
    """No script, stylesheet or font from the network: the built-in theme, highlight.js off."""
    remote = re.compile(r"""<(?:script|link|img)[^>]+(?:src|href)=["'](?:https?:)?//""", re.IGNORECASE)
    hits = [p.name for p in site.rglob("*.html") if remote.search(p.read_text(encoding="utf-8"))]
    assert hits == []


def test_a_broken_reference_fails_the_build(tmp_path):
    """Warnings are errors: a page naming a module that does not exist stops the build."""
    for folder in ("docs", "experiments/figures"):
        shutil.copytree(ROOT / folder, tmp_path / folder)
    shutil.copy(ROOT / "README.md", tmp_path)
    config = (ROOT / "mkdocs.yml").read_text()
    (tmp_path / "mkdocs.yml").write_text(config.replace("paths: [src]", f"paths: [{ROOT / 'src'}]"))
    (tmp_path / "docs" / "api" / "config.md").write_text("# Broken\n\n::: neuromotor.no_such_module\n")
    out = _build(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert out.returncode != 0 and "no_such_module" in out.stderr
