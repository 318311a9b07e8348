"""Fields that mean something only together are checked together, naming the field, before any
computation: a config whose parts disagree is refused, never run with one part silently
replaced or ignored."""

from __future__ import annotations

import math
import re

import pytest

from neuromotor.config import ConfigError, simulation_config
from neuromotor.config.parse import fit_spec

BALL = {"radius": 0.1, "mass": 1.0, "position": [0.0, 1.0, 2.0], "speed": 5.0, "target": "chest"}
FREE = {"root": "free"}
FEATURES = {"kind": "features", "case": [{"peak_deviation_deg": {"value": 1.0, "sd": 0.5, "source": "illustrative"}}]}


@pytest.mark.parametrize(
    ("data", "field"),
    [
        # The postural loop stands on the ground: a driven root is held on its path, and a free
        # root without the ground has nothing to stand on.
        ({"balance": {"enabled": True}}, "balance.enabled"),
        ({"sim": FREE, "ground": {"enabled": False}, "balance": {"enabled": True}}, "balance.enabled"),
        # One ground for the ball and the bodies: its height is [ground]'s, and the ball hits it.
        ({"sim": FREE, "ball": {**BALL, "ground_height": 0.7}}, "ball.ground_height"),
        ({"sim": FREE, "ball": {**BALL, "ground": False}}, "ball.ground"),
        # A ball cannot leave before the simulation starts.
        ({"sim": {"start": 0.8}, "ball": {**BALL, "launch": 0.5}}, "ball.launch"),
        # A moving platform moves the bodies' ground, not the ball's.
        ({"sim": FREE, "ball": BALL,
          "perturbation": [{"kind": "base", "unit": "g", "magnitude": 0.1, "direction": "forward"}]},
         "perturbation[0].kind"),
        # A number that is not one is refused at the field, not found later as a divergence.
        ({"perturbation": [{"body": "chest", "magnitude": 1.0, "point": [math.nan, 0.0, 0.0]}]}, "perturbation[0].point"),
        ({"ball": {**BALL, "position": [0.0, math.inf, 2.0]}}, "ball.position"),
        # A delay too long for any history names the delay the user gave, not the buffer.
        ({"sim": FREE, "balance": {"delay": 5.0}}, "balance.delay"),
        ({"reflex": {"delay": 5.0}}, "reflex.delay"),
    ],
)
def test_parts_that_disagree_are_refused_naming_the_field(data, field):
    with pytest.raises(ConfigError, match=rf"^x\.toml: field '{re.escape(field)}'"):
        simulation_config(data, "x.toml")


def test_a_ball_without_a_launch_time_leaves_when_the_simulation_starts():
    """Its onset (what recovery time is measured from) is then when it actually flies."""
    cfg = simulation_config({"sim": {"start": 0.8}, "ball": BALL}, "x.toml")
    assert cfg.ball.launch == 0.8
    assert simulation_config({"sim": {"start": 0.8}, "ball": {**BALL, "launch": 1.0}}, "x.toml").ball.launch == 1.0
    # On the ground the ball bounces on it: given once, in [ground].
    assert simulation_config({"sim": FREE, "ball": BALL, "ground": {"height": 0.1}}, "x.toml").ground_on


def test_a_fits_step_count_is_a_whole_number():
    cfg = simulation_config({"perturbation": [{"body": "chest", "magnitude": 1.0}]}, "x.toml")
    assert fit_spec({"fit": {"target": FEATURES, "max_steps": 7}}, cfg).options.max_steps == 7
    with pytest.raises(ConfigError, match=r"field 'fit\.max_steps'"):
        fit_spec({"fit": {"target": FEATURES, "max_steps": 2.5}}, cfg)
