"""An inverse response: the PV first going the other way after a push from rest (a drum
level's swell, a column's inverse response: a right-half-plane zero). The FOPDT, SOPDT and
IPDT models have no term for it, so the Ms they predict is optimistic on such a process; the
step test, the relay's first push and the ramp's first trial each look for it, by this test.
"""

from __future__ import annotations

import numpy as np

from services.autotuner.identify.model_fit import ProcessFit

DIP_SIGMAS = 6.0  # the dip must pass this many σ of the noise
DIP_SHARE = 0.04  # and this share of the response's own scale


def dip(along: np.ndarray, noise: float, scale: float) -> float | None:
    """How far the PV went the other way (PV units), ``along`` being the PV from its rest
    signed so that the push's way is positive, when more than ``DIP_SIGMAS`` σ of the
    ``noise`` and ``DIP_SHARE`` of ``scale`` (PV units: the cycle's amplitude, how far the
    PV went the push's way); None otherwise."""
    if along.size == 0:
        return None
    clear = max(DIP_SIGMAS * noise, DIP_SHARE * scale, 1e-12)
    # before the PV first went clearly the push's way: an inverse response comes first; once
    # it has, a swing below the rest is an oscillation about the new level (a trial near K_u
    # grows through its rest)
    ahead = along >= clear
    if np.any(ahead):
        along = along[: int(np.argmax(ahead)) + 1]
    away = float(-np.min(along))
    return away if away > clear else None


def note(where: str, away: float, model: ProcessFit | None) -> str:
    """The warning for a dip of ``away`` PV units seen ``where`` (e.g. "in the relay's first
    push")."""
    fitted = f"the {model.kind.upper()} model" if model else "a low-order model"
    return (
        f"inverse response: {where} the PV first went {away:.3g} the other way from its "
        f"rest: a right-half-plane zero, which {fitted} has no term for, so the robustness "
        "it predicts for the rules (Ms, margins) is optimistic on this process: derivative "
        "action is offered, not recommended"
    )
