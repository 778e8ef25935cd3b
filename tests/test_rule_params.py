"""The rules' parameters read without torch (ctgpp.rule_params) are the constructors' own."""

from __future__ import annotations

import pytest

from ctgpp.behaviours import behaviours
from ctgpp.guidance import describe_rules, registered_losses
from ctgpp.guidance.composite import resolve_params as resolve_live
from ctgpp.guidance.composite import rule_params_of
from ctgpp.rule_params import resolve_params, rule_params, snapshot_text


def test_snapshot_matches_the_guidance_rules() -> None:
    """assets/rule_params.json is what scripts/rule_params.py writes from the constructors today."""
    live = [rule_params_of(r) for r in describe_rules()]
    assert snapshot_text(list(rule_params().values())) == snapshot_text(live), (
        "a guidance rule's parameters changed: run python scripts/rule_params.py"
    )
    assert set(rule_params()) == set(registered_losses())


def test_every_behaviour_has_its_rules_parameters() -> None:
    for name, b in behaviours().items():
        assert b.params == list(rule_params()[b.rule].params), name
        assert b.couples_agents == bool(getattr(registered_losses()[b.rule], "couples_agents", False))


@pytest.mark.parametrize(("rule", "given"), [
    ("speed_limit", {"limit": "3"}),
    ("keep_distance", {"follower": "2", "leader": "1", "max_m": "25"}),
    ("goal_waypoint", {"vehicle": "1/2", "x": "1.5/2", "y": "3;4", "target_speed_mps": "none"}),
    ("target_speed", {"speed_mps": 4.0, "absolute_steps": "yes"}),
    ("lane_change", {"vehicle": 3, "side": "right"}),
    ("stop", {}),
])
def test_resolve_reads_parameters_as_the_constructor_takes_them(rule: str, given: dict) -> None:
    assert resolve_params(rule_params()[rule], given) == resolve_live(rule, **given)


@pytest.mark.parametrize(("rule", "given", "words"), [
    ("speed_limit", {"limit_mps": "90"}, "speeds must be 0 to 40 m/s"),
    ("speed_limit", {"limit_mps": "nan"}, "expected a finite number"),
    ("speed_limit", {"speed": "3"}, "has no parameter 'speed'"),
    ("keep_distance", {"follower": "2"}, "needs leader"),
    ("lane_change", {"vehicle": "two"}, "expects int"),
])
def test_resolve_refuses_what_the_constructor_refuses(rule: str, given: dict, words: str) -> None:
    with pytest.raises(ValueError, match=words):
        resolve_params(rule_params()[rule], given)
    with pytest.raises(ValueError, match=words):
        resolve_live(rule, **given)
