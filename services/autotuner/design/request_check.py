"""Can this request be designed from? The rule asked for must be one whose needs the method's
identification meets (``rules.Rule.kind`` against the registry's ``gives``), and the limits
and step size must make sense. Pure: the request is read by attribute (the bus's
``TuneRequest`` or anything with the same fields), so the tuner and the offline analysis judge
it alike."""

from __future__ import annotations

import math
from typing import Protocol

from services.autotuner.design.rules import check_rule
from services.autotuner.identify.methods import METHODS
from services.autotuner.identify.repeated_steps import MAX_REPEAT
from shared.control.forms import MIN_STEP


class Request(Protocol):
    """The fields of a tune request this check reads."""

    rule: str
    method: str
    pv_limits: tuple[float, float] | None
    step_size: float | None
    repeat: int | str | None


def _giving(kind: str) -> list[str]:
    return [name for name, m in METHODS.items() if kind in m.gives]


def validate_request(req: Request) -> None:
    """ValueError naming the field when the request cannot be run."""
    if req.rule != "auto":
        try:
            rule = check_rule(req.rule)
        except ValueError as err:
            raise ValueError(f"rule: {err}; or auto") from None
        if req.method not in _giving(rule.kind):
            names = _giving(rule.kind)
            need = {
                "open": f"a step test (method {'/'.join(names)})",
                "closed": f"K_u and P_u ({'/'.join(names)})",
                "model": f"a process model ({' or '.join(names)})",
            }[rule.kind]
            raise ValueError(f"rule: {req.rule} needs {need}, not method {req.method}")
    if req.pv_limits and not req.pv_limits[0] < req.pv_limits[1]:
        raise ValueError(f"pv_limits: low must be below high, got {list(req.pv_limits)}")
    if req.step_size is not None and not (
        math.isfinite(req.step_size) and abs(req.step_size) >= MIN_STEP
    ):
        raise ValueError(f"step_size: must be a number of % at least {MIN_STEP:g} in size")
    repeat = req.repeat
    if repeat is not None:
        if req.method != "step":
            raise ValueError(f"repeat: repeated tests are step tests, not method {req.method}")
        if repeat != "auto" and not 1 <= repeat <= MAX_REPEAT:
            raise ValueError(f"repeat: {repeat} tests: must be 1–{MAX_REPEAT}, or auto")
