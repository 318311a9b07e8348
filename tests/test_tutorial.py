"""The tutorial notebook (docs/tutorial.ipynb) runs top to bottom in a real Jupyter kernel
(nbclient + ipykernel) on a short window (0.8 s to 1.25 s, the README example's, so the compiled
programs are shared), and its cells compute what the text says they do. The repository's copy
carries no outputs."""

from __future__ import annotations

import json
import pathlib
import sys

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOK = pathlib.Path(__file__).resolve().parents[1] / "docs" / "tutorial.ipynb"
WINDOW_LINE = "START, DURATION = 0.5, 1.5"
SHORT_LINE = "START, DURATION = 0.8, 0.45"
# Run after the notebook's own cells: what the test checks, as one JSON line.
SUMMARY = """import json, sys
print("SUMMARY " + json.dumps({
    "python": sys.executable, "bodies": model.n_bodies, "dofs": model.n_dofs,
    "mass": float(jnp.sum(model.mass)), "peak": metrics["peak_deviation_deg"], "n_steps": len(np.load(run_path)["time"]),
    "sweep": [[r["magnitude"], r["peak_deviation_deg"]] for r in sweep.rows],
    "sweep_files": sorted(p.name for p in files.values()),
    "fit": [fitted.status, fitted.ks, fitted.kd], "grad": [float(g) for g in grad]}))"""


def test_repository_copy_has_no_outputs():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(c.outputs == [] and c.execution_count is None for c in code)
    assert sum(WINDOW_LINE in c.source for c in code) == 1


@pytest.fixture(scope="module")
def executed(tmp_path_factory):
    nb = nbformat.read(NOTEBOOK, as_version=4)
    for cell in nb.cells:
        cell.source = cell.source.replace(WINDOW_LINE, SHORT_LINE)
    nb.cells.append(nbformat.v4.new_code_cell(SUMMARY))
    folder = tmp_path_factory.mktemp("tutorial")
    NotebookClient(nb, timeout=900, kernel_name="python3",
                   resources={"metadata": {"path": str(folder)}}).execute()
    return nb


def _summary(nb) -> dict:
    text = "".join(o.get("text", "") for o in nb.cells[-1].outputs if o.output_type == "stream")
    return json.loads(text.split("SUMMARY ", 1)[1])


def test_every_cell_ran_without_error(executed):
    code = [c for c in executed.cells if c.cell_type == "code"]
    assert [c.execution_count for c in code] == list(range(1, len(code) + 1))
    assert not [o for c in code for o in c.outputs if o.output_type == "error"]
    assert _summary(executed)["python"] == sys.executable   # the kernel runs this environment


def test_cells_compute_what_the_text_says(executed):
    s = _summary(executed)
    assert (s["bodies"], s["dofs"]) == (19, 54) and 55 < s["mass"] < 70
    assert s["n_steps"] == 55 and s["peak"] > 0.5                 # 0.45 s at 1/120 s; the hit shows
    magnitudes, peaks = zip(*s["sweep"])
    assert magnitudes == (100.0, 200.0, 400.0) and 0 < peaks[0] < peaks[1] < peaks[2]
    assert "sweep.csv" in s["sweep_files"]
    status, ks, kd = s["fit"]
    assert status == "converged" and ks == pytest.approx(250.0, rel=1e-3) and kd == pytest.approx(25.0, rel=1e-3)
    assert s["grad"][0] < 0                                      # stiffer feedback, smaller peak


def test_viewer_is_shown_inline(executed):
    shown = [o for c in executed.cells if "neuromotor.viz.show" in c.source for o in c.outputs]
    assert len(shown) == 1 and shown[0].output_type == "execute_result"
    page = shown[0]["data"]["text/html"]
    assert page.startswith("<iframe srcdoc=") and "nm-data" in page and "three" in page
