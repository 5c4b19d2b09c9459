"""Whether the PV's drift when a test began spoils the test's figures.

The tuner waits for rest over a window it chooses before it knows the process: 40 samples for
a loop in manual (``shared.control.rest_window``), seconds where the process's lags may be
minutes. A process still settling from an earlier change then passes as at rest, its drift
within 3σ over the window, and the test's figures carry the drift: a step test of
e^{−5s}/((100s + 1)(5s + 1)) begun 8 s into a 1.5 % output change's settling read its static
gain 0.83 for 1.0 and an inverse response that was not there (helper trial). Once the test is
over its length and the PV's swing in it are known, and the drift seen at rest, where it is
clear of its own noise, says how much of that swing it may be.
"""

from __future__ import annotations

import math

from services.autotuner.identify.experiments import Identification
from services.autotuner.identify.reaction_curve import IntegratingCurve, ReactionCurve
from services.autotuner.identify.relay_result import RelayResult

# the drift counts where it stands this many standard errors clear of a fit to white noise
SIGNIFICANT = 4.0
# … and, carried over the test, is at least this share of the PV's swing in it
SHARE = 0.1


def drift_note(
    drift: float | None,
    noise: float | None,
    window: float | None,
    sample_time: float,
    duration: float,
    swing: float | None,
    units: str = "",
) -> str | None:
    """What the engineer must know when the PV drifted ``drift`` (PV units/s, the rest check's
    straight line over its ``window`` s, noise σ ``noise``) as a test of ``duration`` s began
    whose PV swung by ``swing`` (PV units): None when the drift is within what white noise
    gives such a fit (``SIGNIFICANT`` standard errors: σ·√12/(W·√n)) or, over the test, under
    ``SHARE`` of the swing."""
    if not drift or not noise or not window or not swing or duration <= 0:
        return None
    n = max(3, round(window / sample_time))
    se = noise * math.sqrt(12.0 / n) / window
    if abs(drift) < SIGNIFICANT * se:
        return None
    over = abs(drift) * duration
    if over < SHARE * abs(swing):
        return None
    u = f" {units}" if units else ""
    return (
        f"the PV was still drifting ({drift:+.3g}{u}/s, {abs(drift) / se:.0f} standard errors "
        f"of its noise) when the test began, judged at rest over {window:.3g} s: at that rate, "
        f"over the test's {duration:.4g} s, {over:.3g}{u}, {100 * over / abs(swing):.0f} % of "
        "the PV's swing in it, so its figures may carry the drift; a --rest-window about the "
        "process's time scale waits for its rest"
    )


def swing_of(ident: Identification) -> float | None:
    """The PV's swing in the test (PV units): a step test's change (an integrating one's to
    where the step ended), a relay's cycle peak to peak; None for a ramp (its trials hold
    the loop in auto, which works against a drift)."""
    if isinstance(ident.step, ReactionCurve):
        return ident.step.pv_after - ident.step.pv_before
    if isinstance(ident.step, IntegratingCurve):
        return ident.step.pv_peak - ident.step.pv_before
    if isinstance(ident.experiment, RelayResult):
        return 2.0 * ident.experiment.amplitude
    return None


def drift_notes(
    ident: Identification,
    rest: dict | None,
    sample_time: float,
    t_first: float | None,
    t_end: float | None,
    units: str = "",
) -> list[str]:
    """``drift_note`` of a test whose first sample came at ``t_first`` and whose last fed one
    at ``t_end`` (s), the rest check's figures ``rest`` (the result's ``rest``): the same
    words live and offline (``analyze`` reads the rest from the recorded result)."""
    if not rest or t_first is None or t_end is None:
        return []
    note = drift_note(
        rest.get("drift"),
        rest.get("noise_std"),
        rest.get("window"),
        sample_time,
        t_end - t_first,
        swing_of(ident),
        units,
    )
    return [] if note is None else [note]
