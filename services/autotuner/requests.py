"""A tune request at the edge: checked (``validate_request``) and turned into the plain
``Settings`` the experiments take (``settings_of``), with the defaults the README lists."""

from __future__ import annotations

import math

from services.autotuner.design.rules import check_rule
from services.autotuner.identify.experiments import Settings
from services.autotuner.identify.methods import METHODS
from shared.messages import TuneRequest

DEFAULT_RELAY_AMPLITUDE = 5.0  # %: also the load step of the verification
DEFAULT_STEP_SIZE = 5.0  # %
DEFAULT_BUMP_FRACTION = 0.01  # of the PV range, ramp setpoint bump


def settings_of(req: TuneRequest) -> Settings:
    """What the request asks of the experiment, defaults filled in."""
    return Settings(
        amplitude=req.amplitude or DEFAULT_RELAY_AMPLITUDE,
        hysteresis=req.hysteresis,
        cycles=req.cycles,
        tolerance=req.tolerance,
        relay_bias=req.relay_bias or 0.0,
        step_size=req.step_size or DEFAULT_STEP_SIZE,
        max_time=req.max_time,
    )


def _giving(kind: str) -> list[str]:
    return [name for name, m in METHODS.items() if kind in m.gives]


def validate_request(req: TuneRequest) -> None:
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
    if req.step_size is not None and not (math.isfinite(req.step_size) and req.step_size != 0):
        raise ValueError("step_size: must be a non-zero number of %")
