"""mkdocs hooks: the site's front page is the repository's README (one source for both), the
tutorial page points at the notebook, and files a page links outside docs/ (figures under
experiments/) are copied in under repo/ so that the links resolve offline."""

from __future__ import annotations

import pathlib
import posixpath
import re

from mkdocs.structure.files import File

OUTSIDE = re.compile(r"\]\((\.\./[^)\s#]+)\)")   # a Markdown link that leaves docs/
TUTORIAL = """# Tutorial

The tutorial is a Jupyter notebook, [`docs/tutorial.ipynb`](tutorial.ipynb): load a clip,
inspect the body, hit it, look at the result inline with `neuromotor.viz.show`, run a small
sweep, fit (ks, kd) to a synthetic target and take a gradient through the simulation. Open it
in any Jupyter front end (JupyterLab, Notebook, VS Code) with a kernel from the project's
environment (`pip install -e '.[notebook]'` adds ipykernel; the front end is yours to install);
the test suite runs it top to bottom (`tests/test_tutorial.py`).
"""


def _dirs(config) -> tuple[pathlib.Path, pathlib.Path]:
    """The repository (where mkdocs.yml is) and docs/."""
    return pathlib.Path(config.config_file_path).resolve().parent, pathlib.Path(config["docs_dir"]).resolve()


def _outside_links(page: pathlib.Path, root: pathlib.Path, docs: pathlib.Path):
    """(link as written, repository path) of each link in ``page`` that points outside docs/."""
    for link in OUTSIDE.findall(page.read_text(encoding="utf-8")):
        target = (page.parent / link).resolve()
        if target.is_file() and docs not in target.parents and root in target.parents:
            yield link, target.relative_to(root).as_posix()


def on_files(files, config):
    root, docs = _dirs(config)
    readme = (root / "README.md").read_text(encoding="utf-8").replace("](docs/", "](")
    files.append(File.generated(config, "index.md", content=readme))
    files.append(File.generated(config, "tutorial.md", content=TUTORIAL))
    copied = {rel for page in docs.rglob("*.md") for _, rel in _outside_links(page, root, docs)}
    for rel in sorted(copied):
        files.append(File.generated(config, f"repo/{rel}", content=(root / rel).read_bytes()))
    return files


def on_page_markdown(markdown, page, config, files):
    source = page.file.abs_src_path
    if not source:
        return markdown
    src = pathlib.Path(source)
    here = posixpath.dirname(page.file.src_uri)
    for link, rel in _outside_links(src, *_dirs(config)):
        markdown = markdown.replace(f"]({link})", f"]({posixpath.relpath(f'repo/{rel}', here or '.')})")
    return markdown


# Docstrings use Sphinx roles (":func:`step`"); Markdown renders the name as code and leaves the
# role in front of it.
ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|obj|exc):(?=<code)")


def on_page_content(html, page, config, files):
    return ROLE.sub("", html)
