"""Every ``--json`` prints strict JSON: a figure that is not finite goes out as null.

``autotune analyze --json`` printed ``"ku_describing_function": Infinity`` for a relay whose
cycle stayed inside its hysteresis (lvl2 at a given 5 %): not JSON, so ``jq`` and every
strict parser refused the whole output.
"""

from __future__ import annotations

import json
import math

import pytest

from services.autotuner.identify.relay_result import RelayResult
from shared import json_text


def _strict(text: str):
    def refuse(constant: str):
        raise ValueError(f"not JSON: {constant}")

    return json.loads(text, parse_constant=refuse)


def test_figures_that_are_not_finite_go_out_as_null_at_any_depth():
    obj = {"a": math.inf, "b": [math.nan, 1.5, (-math.inf, 2)], "c": {"d": {"e": math.nan}}}
    assert _strict(json_text.dumps(obj)) == {
        "a": None,
        "b": [None, 1.5, [None, 2]],
        "c": {"d": {"e": None}},
    }
    with pytest.raises(ValueError):
        _strict(json.dumps(obj))  # what it printed before


def test_finite_figures_keep_their_value_to_the_bit():
    x = 0.1 + 0.2
    assert _strict(json_text.dumps({"x": x, "n": 3, "s": "inf", "t": True})) == {
        "x": x,
        "n": 3,
        "s": "inf",
        "t": True,
    }


def test_a_relay_cycle_inside_its_hysteresis_reads_as_null():
    r = RelayResult(
        ku=math.nan, pu=math.nan, amplitude=0.006, relay_amplitude=5.0, hysteresis=0.0068,
        bias=50.0, noise_std=0.0023, cycles=6, ku_spread=0.0, pu_spread=0.0, rest_pv=1.5,
        ku_df=math.inf, pu_df=46.2, crossing="not reached",
    )  # fmt: skip
    out = _strict(json_text.dumps({"experiment": r.to_dict()}))
    assert out["experiment"]["ku_describing_function"] is None
    assert out["experiment"]["pu_describing_function"] == 46.2
