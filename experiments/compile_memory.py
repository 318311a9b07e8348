"""Peak resident memory of a cold ``neuromotor simulate`` process (nothing cached, so every
program is compiled) in float64 and float32, on every shipped clip and on synthetic rigs: the
table of docs/benchmarks.md, "Compile memory".

    .venv/bin/python experiments/compile_memory.py [--duration 0.1] [--limit-gb 4]

Each run is a subprocess under an address-space limit (a blow-up fails instead of filling the
machine); its peak RSS is the process's own ``VmHWM`` (``tests/peak_rss.py``).
"""

import argparse
import os
import pathlib
import subprocess
import sys
import tempfile

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "mocap"
sys.path.insert(0, str(REPO / "tests"))

from synthetic_rigs import make_rig  # noqa: E402

# The rig of issue 35's report: a 23-joint walk in inches, a thumb and a Hand_End joint under
# each hand; and a 6-channel, bent-zero-pose one.
RIGS = {
    "synthetic 23-joint, inches, thumbs, Hand_End": dict(
        seed=5, unit="in", fingers=False, toes=False, face=False, props=0, twist=False, hip_link=False,
        thumbs=True, hand_end=True, frames=120),
    "synthetic 23-joint, 6 channels, bent zero pose, Z up": dict(
        seed=2, unit="in", fingers=False, toes=False, face=False, props=0, twist=False, hip_link=False,
        thumbs=True, hand_end=True, frames=120, up="Z"),
}
H = {"bandai_kick_22joint_6ch": 1 / 360}  # the step its spinning root needs (docs/float32.md)


def measure(clip: pathlib.Path, dtype: str, duration: float, limit: int, h: float, work: pathlib.Path):
    """(peak RSS in GB, exit status) of one cold ``neuromotor simulate``."""
    cfg = work / f"{clip.stem}_{dtype}.toml"
    cfg.write_text(f'clip = "{clip}"\n[sim]\nh = {h!r}\nstart = 1.0\nduration = {duration}\ndtype = "{dtype}"\n')
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR")}
    env.update(NEUROMOTOR_CACHE_DIR="off", PYTHONPATH=str(REPO / "src"))
    peak = work / "peak_kb.txt"
    peak.unlink(missing_ok=True)
    proc = subprocess.run(
        [sys.executable, str(REPO / "tests" / "peak_rss.py"), str(limit), str(peak), "simulate", str(cfg), "-o",
         str(work / "run.npz")], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return (int(peak.read_text()) / 1e6 if peak.exists() else float("nan")), proc.returncode


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=0.1, help="simulated window, s")
    ap.add_argument("--limit-gb", type=float, default=4.0, help="address-space limit of each run (a run maps about 2.1 GB)")
    args = ap.parse_args()
    limit = int(args.limit_gb * 1e9)
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(tmp)
        clips = {p.stem: p for p in sorted(SHARED.glob("*.bvh"))}
        for name, opts in RIGS.items():
            path = work / f"rig{opts['seed']}.bvh"
            path.write_text(make_rig(**opts).text)
            clips[name] = path
        print("| clip | peak RSS float64 (GB) | peak RSS float32 (GB) |")
        print("| --- | --- | --- |")
        for name, path in clips.items():
            cells = []
            for dtype in ("float64", "float32"):
                gb, rc = measure(path, dtype, args.duration, limit, H.get(name, 1 / 120), work)
                cells.append(f"{gb:.2f}" + ("" if rc == 0 else f" (exit {rc})"))
            print(f"| {name} | {cells[0]} | {cells[1]} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
