"""Compile memory stays bounded (issue 35): a cold float32 ``neuromotor simulate`` of a 23-joint
walk in inches with a thumb and a Hand_End joint under each hand (the rig of the report whose
float32 compile grew past 24 GB) peaks below 2 GB resident. Figures for every shipped clip, in
both precisions: docs/benchmarks.md, "Compile memory".

The run is a subprocess with nothing cached (every program compiles, as on a user's first run),
with the user's XLA options (the suite's fast-compile flags removed), under an address-space
limit so that a regression fails at the limit instead of filling the machine; the peak is the
process's own (``tests/peak_rss.py``), not the pytest worker it was forked from.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys

from synthetic_rigs import make_rig

REPO = pathlib.Path(__file__).resolve().parents[2]
PEAK_LIMIT_GB = 2.0
ADDRESS_SPACE = 4 * 10**9  # bytes; a normal run maps at most about 2.1 GB (VmPeak)
# Same rig as experiments/compile_memory.py's first synthetic row.
RIG = dict(seed=5, unit="in", fingers=False, toes=False, face=False, props=0, twist=False, hip_link=False,
           thumbs=True, hand_end=True, frames=120)


def test_float32_simulate_compiles_in_bounded_memory(tmp_path):
    rig = make_rig(**RIG)
    assert len(rig.names) == 23
    clip = tmp_path / "walk_in_inches.bvh"
    clip.write_text(rig.text)
    cfg = tmp_path / "f32.toml"
    cfg.write_text(f'clip = "{clip}"\n[sim]\nstart = 1.0\nduration = 0.1\ndtype = "float32"\n')
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR")}
    env.update(NEUROMOTOR_CACHE_DIR="off", PYTHONPATH=os.pathsep.join([str(REPO / "src"), env.get("PYTHONPATH", "")]))
    log, peak = tmp_path / "stderr.txt", tmp_path / "peak_kb.txt"
    with open(log, "w") as err:
        proc = subprocess.run([sys.executable, str(REPO / "tests" / "peak_rss.py"), str(ADDRESS_SPACE), str(peak),
                               "simulate", str(cfg), "-o", str(tmp_path / "r.npz")],
                              env=env, stdout=subprocess.DEVNULL, stderr=err, timeout=400)
    assert proc.returncode == 0, (f"float32 simulate failed (exit {proc.returncode}) under "
                                  f"{ADDRESS_SPACE / 1e9:.0f} GB of address space:\n{log.read_text()[-2000:]}")
    peak_gb = int(peak.read_text()) / 1e6  # kB
    assert peak_gb < PEAK_LIMIT_GB, f"float32 simulate peaked at {peak_gb:.2f} GB resident"
