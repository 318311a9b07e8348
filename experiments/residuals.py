"""The residuals of the contact-aware inverse dynamics (issue 38; docs/residuals.md): per clip,
the residual root force and moment the ground reaction forces leave, RMS and peak in N, N m and
% of body weight, the fraction of steps with contact, and the flight phases' residual (there
the whole wrench m (a_com - g), dL/dt: the capture's own consistency).

    .venv/bin/python experiments/residuals.py [CLIP.bvh ...] [--start 0] [--duration SECONDS]

Default: the shipped walk and the CMU jumps, whole clips, h = 1/120 s.
"""

import argparse
import time

import numpy as np

import _common  # noqa: F401

from neuromotor.model.load import load_character
from neuromotor.physics.dynamics import StepOptions, make_reference
from neuromotor.studies import residuals as rs

SHARED = _common.REPO.parent / "shared" / "mocap"
CLIPS = [SHARED / "walk_22joint_zyx.bvh", SHARED / "cmu_01_01_jumps_31joint.bvh"]


def figures(path, start: float, duration: float | None, h: float):
    character, traj = load_character(path)
    clip = character.clip
    span = (clip.n_frames - 1) * clip.frame_time - start if duration is None else duration
    options = StepOptions(h=h, n_steps=int(np.floor(span / h + 1e-9)))
    t0 = time.perf_counter()
    ref = make_reference(character.model, traj, start, options)
    res = rs.capture_residuals(character, traj, ref, options)
    return res, rs.residual_summary(res), time.perf_counter() - t0


def show(path, res, s: dict, seconds: float) -> None:
    print(f"\n{path.name}: {s['steps']} steps from {res.time[0]:.3f} s ({seconds:.0f} s to compute)")
    print(f"  body weight {s['body_weight_N']:.1f} N, stature {s['stature_m']:.3f} m, floor {s['floor_m']:+.4f} m")
    print(f"  contact: height < {s['contact_height_m']} m, speed < {s['contact_speed_m_s']} m/s, mu {s['friction']}")
    print(f"  steps with contact {100 * s['contact_fraction']:.1f} %, flight {100 * s['flight_fraction']:.1f} %")
    if s["grf_peak_N"] is not None:
        print(
            f"  peak ground reaction force {s['grf_peak_N']:.1f} N ({s['grf_peak_N'] / s['body_weight_N']:.2f} BW): "
            f"residual force RMS {100 * s['force_rms_N'] / s['grf_peak_N']:.2f} %, "
            f"peak {100 * s['force_peak_N'] / s['grf_peak_N']:.1f} % of it"
        )
    for prefix, what in (("", "all steps"), ("flight_", "flight steps")):
        if s[f"{prefix}force_rms_N"] is None:
            print(f"  {what}: none")
            continue
        print(
            f"  {what}: residual force RMS {s[f'{prefix}force_rms_N']:.1f} N "
            f"({s[f'{prefix}force_rms_pct_bw']:.2f} % BW), peak {s[f'{prefix}force_peak_N']:.1f} N "
            f"({s[f'{prefix}force_peak_pct_bw']:.1f} % BW); moment about the COM RMS "
            f"{s[f'{prefix}moment_rms_Nm']:.1f} N m ({s[f'{prefix}moment_rms_pct_bw_stature']:.2f} % BW x stature), "
            f"peak {s[f'{prefix}moment_peak_Nm']:.1f} N m ({s[f'{prefix}moment_peak_pct_bw_stature']:.1f} %)"
        )
    contact = ~res.flight
    if contact.any():
        force = np.linalg.norm(res.residual[contact, :3], axis=-1)
        print(
            f"  contact steps: residual force RMS {np.sqrt(np.mean(force**2)):.1f} N "
            f"({100 * np.sqrt(np.mean(force**2)) / res.weight:.2f} % BW), peak {force.max():.1f} N"
        )
    phases = rs.flight_phases(res.flight)
    if phases:
        means = rs.flight_means(res)
        print("  flight phases: start s, duration s, mean residual force N (% BW), RMS N, mean moment N m")
        for (a, b), m in zip(phases, means):
            rms = np.sqrt(np.mean(np.sum(res.residual[a:b, :3] ** 2, -1)))
            f = np.linalg.norm(m[:3])
            print(
                f"    {res.time[a]:7.3f} {res.time[b - 1] - res.time[a] + (res.time[1] - res.time[0]):6.3f} "
                f"{f:8.1f} ({100 * f / res.weight:5.1f}) {rms:8.1f} {np.linalg.norm(m[3:]):8.1f}"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("clips", nargs="*", default=[str(p) for p in CLIPS])
    ap.add_argument("--start", type=float, default=0.0, help="window start (s)")
    ap.add_argument("--duration", type=float, default=None, help="window length (s; default: to the clip's end)")
    ap.add_argument("--h", type=float, default=1.0 / 120.0, help="time step (s)")
    args = ap.parse_args(argv)
    for clip in args.clips:
        path = _common.pathlib.Path(clip)
        res, summary, seconds = figures(path, args.start, args.duration, args.h)
        show(path, res, summary, seconds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
