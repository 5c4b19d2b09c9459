"""Request validation: every refusal names its field and says why, and every rule is accepted
with exactly the methods that give what it needs (closed-loop rules K_u and P_u: relay or
ramp; open-loop rules a step test; model rules a process model: relay or step)."""

from __future__ import annotations

import math

import pytest

from services.autotuner.design.request_check import validate_request
from services.autotuner.design.rules import RULES
from shared.messages import TuneRequest

# the ramp's model is the one fitted to its whole record (its own recommendation designs
# from it: `autotune apply` of a ramp run's amigo-pid was refused while tune recommended it)
GIVES = {"closed": {"relay", "ramp"}, "open": {"step"}, "model": {"relay", "ramp", "step"}}


@pytest.mark.parametrize("method", ["relay", "ramp", "step"])
def test_auto_is_accepted_with_every_method(method):
    assert validate_request(TuneRequest(loop="x", method=method)) is None


@pytest.mark.parametrize("rule", sorted(RULES))
@pytest.mark.parametrize("method", ["relay", "ramp", "step"])
def test_each_rule_takes_exactly_the_methods_that_give_what_it_needs(rule, method):
    req = TuneRequest(loop="x", method=method, rule=rule)
    if method in GIVES[RULES[rule].kind]:
        assert validate_request(req) is None
    else:
        with pytest.raises(ValueError, match=rf"^rule: {rule} needs .*, not method {method}$"):
            validate_request(req)


@pytest.mark.parametrize(
    ("rule", "method", "message"),
    [
        ("zn-pid", "step", "rule: zn-pid needs K_u and P_u (relay/ramp), not method step"),
        ("zn-ol-pi", "relay", "rule: zn-ol-pi needs a step test (method step), not method relay"),
        ("zn-ol-pid", "ramp", "rule: zn-ol-pid needs a step test (method step), not method ramp"),
    ],
)
def test_the_refusal_says_what_the_rule_needs(rule, method, message):
    with pytest.raises(ValueError) as err:
        validate_request(TuneRequest(loop="x", method=method, rule=rule))
    assert str(err.value) == message


def test_an_unknown_rule_lists_the_known_ones():
    with pytest.raises(ValueError) as err:
        validate_request(TuneRequest(loop="x", rule="zn-magic"))
    assert (
        str(err.value)
        == f"rule: unknown rule 'zn-magic'; expected one of {', '.join(RULES)}; or auto"
    )


@pytest.mark.parametrize("limits", [(60.0, 40.0), (50.0, 50.0)])
def test_pv_limits_must_be_ordered(limits):
    with pytest.raises(ValueError) as err:
        validate_request(TuneRequest(loop="x", pv_limits=limits))
    assert str(err.value) == f"pv_limits: low must be below high, got {list(limits)}"


def test_ordered_pv_limits_are_accepted():
    assert validate_request(TuneRequest(loop="x", pv_limits=(40.0, 60.0))) is None


@pytest.mark.parametrize("size", [0.0, -0.0, 1e-9, -0.00999, 1e-300])
def test_a_step_size_must_be_at_least_a_hundredth_of_a_percent(size):
    """1e-9 % on a noise-free loop read K −26 %/% off the PV's rounding and 1e-300 % waited
    past its timeout with the loop held (helper review): below 0.01 % is refused, and the CLI
    refuses it before anything is sent."""
    with pytest.raises(ValueError) as err:
        validate_request(TuneRequest(loop="x", method="step", step_size=size))
    assert str(err.value) == "step_size: must be a number of % at least 0.01 in size"
    assert validate_request(TuneRequest(loop="x", method="step", step_size=0.01)) is None


@pytest.mark.parametrize("size", [math.inf, -math.inf, math.nan])
def test_a_step_size_that_is_not_finite_is_refused_by_the_message_itself(size):
    with pytest.raises(ValueError, match="step_size") as err:
        TuneRequest(loop="x", method="step", step_size=size)
    assert "finite number" in str(err.value)


@pytest.mark.parametrize("size", [-5.0, 0.5, 20.0])
def test_a_step_either_way_is_accepted(size):
    assert validate_request(TuneRequest(loop="x", method="step", step_size=size)) is None
