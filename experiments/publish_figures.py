"""Copy the experiment figures from out/ into experiments/figures/, downscaled to stay small.

    .venv/bin/python experiments/publish_figures.py [--width 900]

Run after the experiment scripts (see experiments/README.md); missing sources are reported.
"""

import argparse
import os
import pathlib
import sys
import tempfile

from PIL import Image

REPO = pathlib.Path(__file__).resolve().parents[1]
FIGURES = {
    "out/exp_arm/arm.png": "arm.png",
    "out/exp_arm/filmstrip.png": "arm_filmstrip.png",
    "out/exp_full_body/filmstrip.png": "full_body_filmstrip.png",
    "out/exp_full_body/deviation.png": "full_body_deviation.png",
    "out/exp_high_gain/contrast.png": "high_gain_contrast.png",
    "out/exp_high_gain/contrast_sweep.png": "high_gain_contrast_sweep.png",
    "out/sweep_magnitude/sweep.png": "sweep_magnitude.png",
    "out/gains_map/gains_map.png": "gains_map.png",
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=900, help="largest width in pixels")
    args = ap.parse_args(argv)
    dest = REPO / "experiments" / "figures"
    dest.mkdir(parents=True, exist_ok=True)
    missing = 0
    for src, name in FIGURES.items():
        path = REPO / src
        if not path.exists():
            print(f"missing {src}", file=sys.stderr)
            missing += 1
            continue
        img = Image.open(path).convert("RGB")
        if img.width > args.width:
            img = img.resize((args.width, round(img.height * args.width / img.width)), Image.LANCZOS)
        fd, tmp = tempfile.mkstemp(suffix=".png", dir=dest)
        os.close(fd)
        img.quantize(256).save(tmp, optimize=True)  # palette PNG: a few tens of kB
        os.replace(tmp, dest / name)
        print(f"{dest / name}: {img.width}x{img.height}, {(dest / name).stat().st_size // 1024} kB")
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
