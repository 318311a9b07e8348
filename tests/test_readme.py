"""The README's Python examples run as written (on a shorter window, to keep the suite quick)."""

import pathlib
import re

import numpy as np

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks() -> list[str]:
    text = README.read_text()
    section = text[text.index("## Python API"):text.index("## Command line")]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_readme_python_examples_run(tmp_path, monkeypatch):
    blocks = _python_blocks()
    assert len(blocks) == 2
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(blocks[0].replace("duration=2.0", "start=0.8, duration=0.45"), scope)  # the hit is at 1.0 s
    assert (tmp_path / "run.npz").is_file()
    assert scope["result"].metrics["peak_deviation_deg"] > 0.1
    call = "jax.jacfwd(peak)(jnp.log(jnp.array([400.0, 20.0])))"
    assert blocks[1].rstrip().endswith(call)
    exec(blocks[1].replace(call, "JAC = " + call), scope)
    jac = np.asarray(scope["JAC"])
    # Stiffer feedback lowers the peak deviation of the hit.
    assert jac.shape == (2,) and np.all(np.isfinite(jac)) and jac[0] < 0
