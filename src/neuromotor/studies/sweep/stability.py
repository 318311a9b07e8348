"""Stability of a reflex grid: each run of a sweep over reflex gain x delay classified as stable,
sustained (an oscillation that does not decay), large or diverged (:mod:`neuromotor.studies.reflex`
draws the map; :mod:`neuromotor.physics.reflex` is the model)."""

from __future__ import annotations

from neuromotor.config.specs import SimulationConfig

STABLE_PEAK_DEG = 45.0  # a run whose deviation exceeds this is not a recovery from a push
DECAY_FRACTION = 0.5  # a stable run ends the window below this fraction of its peak deviation
# Where the paper's controller sits on the stability map: no delayed path, the muscle feedback alone
# (ks = 400 1/s^2 at zero delay, implicit in Eq. 2).
PAPER_FEEDBACK = (0.0, 0.0)


def map_options(cfg: SimulationConfig, bound_deg: float = STABLE_PEAK_DEG) -> dict:
    """Keyword arguments of :func:`neuromotor.viz.reflex_plots.plot_stability_map` for a grid
    on ``cfg``: the bound and the paper's controller (no delayed path) marked."""
    criterion = (
        f"no divergence, peak deviation below {bound_deg:g} deg, and at the window's end below "
        f"{DECAY_FRACTION:g} x the peak"
    )
    return dict(
        criterion=criterion,
        paper=PAPER_FEEDBACK,
        paper_label=f"paper: muscle feedback alone (ks={cfg.ks:g}, kd={cfg.kd:g}, no delay)",
    )


def classify(row: dict, bound_deg: float = STABLE_PEAK_DEG) -> str:
    """``diverged`` (the run or its twin blew up), ``large`` (peak deviation at or beyond
    ``bound_deg``: not a recovery), ``sustained`` (the deviation at the window's end is still
    :data:`DECAY_FRACTION` of its peak or more: the oscillation does not decay) or ``stable``."""
    if row["diverged"]:
        return "diverged"
    if not row["peak_deviation_deg"] < bound_deg:
        return "large"
    return "stable" if row["final_error_deg"] < DECAY_FRACTION * row["peak_deviation_deg"] else "sustained"


def classified(rows: list[dict], bound_deg: float = STABLE_PEAK_DEG) -> list[dict]:
    """``rows`` with the key ``stability`` (:func:`classify`)."""
    return [dict(r, stability=classify(r, bound_deg)) for r in rows]
