"""The verification's gain-margin check of a PID: the loop run for a while at twice the gain.

Why: a relay, ramp or step test measures the process up to its ultimate frequency ω_u, and
the model fitted to it says nothing of what lies beyond. A PI's gain above ω_u stays near
Kc, below the K_u the test measured; a PID's rises to Kc·(1 + N) there (N the derivative
filter's, 10), where no experiment looked. A lightly damped mode of the process beyond ω_u (a
resonance) then takes the loop's margins, and neither the model's predicted Ms nor a setpoint
step, whose ringing at that frequency stays under the noise, shows it: random field plants
with a resonance at 1.5–10·ω_u got AMIGO and ZN PIDs with status ok whose exact gain margins
were 1.0–1.6 (Ms 2.8–222).

Gains within the product's bound Ms ≤ 2 keep a gain margin of at least Ms/(Ms − 1) = 2. So
the check multiplies Kc by ``FACTOR`` = 2 (Ti and Td kept), steps the setpoint by half the
verification's step (the same proportional kick), and watches ``SCALES`` time scales: a loop
with a gain margin under 2 is unstable there and its swing grows (or, its output saturating,
keeps swinging); one with a margin of 2 or more decays, however lightly. The check fails
when the PV swings past ``SWING_BOUND`` times the check's step (cut short there), or when the
swing over its last time scale (RMS less the noise) is over ``LASTING`` of the step, or over
``GROWING`` of it, clear of the noise, and ``GROWTH`` times the least of the time scales
before it (after the first, the kick's own response). Swings are read about each time scale's
own straight line: a slow approach to the setpoint is no swing. Re-run on random field loops
whose PIDs had ended ok: all 17 with an exact gain margin under 1.6 fail it, 3 of the 6
between 1.6 and 2, and none of the 133 with 2 or more (the most swing one of those kept:
0.15 of the step, 1.28 times the least before), nor any of the presets' 14 PID tunes. The
check's record holds ``SCALES`` whole time scales (its length rounded down to a sample lost
the last one, and the one growing loop it missed had its growth in it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FACTOR = 2.0  # the gain margin every gains within Ms ≤ 2 keep: Ms/(Ms − 1)
SCALES = 4  # time scales watched
SWING_BOUND = 3.0  # × the check's step: a swing past it ends the check, failed
LASTING = 0.25  # × the step: a swing this large over the last time scale fails
GROWING = 0.1  # × the step: a swing this large that has grown ...
GROWTH = 1.5  # ... by this factor from the smallest time scale before it fails
# a fast mode the model lacks (``unmodelled_mode``) that rang past the decay ratio limit
# under the gains is watched in the check too: kept this much a period or more at Kc × 2, it
# grows there, so the gains' margin at that mode is under 2 (they took its damping); less,
# the ringing is the process's own (a resonance that no PID gains damp)
MODE_GROWS = 1.0


def factor_for(ms_bound: float) -> float:
    """The gain factor of the check under a request's ``--ms-bound``: ``FACTOR`` (2), or where
    the bound admits gains past Ms 2, the margin Ms/(Ms − 1) those keep (3 → 1.5). Why: the
    check at 2 rejected every gains the larger bound admitted (TL PID on 2·e^{−s}/(10s + 1),
    Ms 2.51 and gain margin 1.67 on the model, asked for with --ms-bound 3: "gain margin
    under 2"), the bound saying one thing and the check another."""
    return min(FACTOR, ms_bound / (ms_bound - 1.0)) if ms_bound > 1.0 else FACTOR


def admitted_ms(factor: float) -> float:
    """The Ms whose gains keep a gain margin of ``factor`` at least: factor/(factor − 1)."""
    return factor / (factor - 1.0)


@dataclass(frozen=True)
class MarginCheck:
    """What the check saw: ``swing``, the RMS swing (about the time scale's straight line,
    less the noise) over its last time scale as a fraction of its step; ``growth``, that over
    the least of the time scales before it (after the first; None: too short a record, or a
    last swing within the noise's σ); ``stopped``, why it was cut short (None: watched to its
    end)."""

    swing: float | None
    growth: float | None
    stopped: str | None = None
    # the fast mode watched (one the gains rang with): its amplitude ratio a period at
    # Kc × FACTOR, and its period, s (None: none watched, or it did not stand out)
    mode: float | None = None
    mode_period: float | None = None

    @property
    def failed(self) -> bool:
        if self.stopped is not None or self.mode_grows:
            return True
        if self.swing is None:
            return False
        grown = self.growth is not None and self.growth >= GROWTH
        return self.swing > LASTING or (self.swing > GROWING and grown)

    @property
    def mode_grows(self) -> bool:
        return self.mode is not None and self.mode >= MODE_GROWS


def swings_of(y: np.ndarray, noise: float, scale_samples: int) -> list[float]:
    """The RMS swing of ``y`` over each whole time scale of ``scale_samples`` samples: about
    the time scale's own straight line (a slow approach to the setpoint is no swing: a lambda
    PID on a lag of 160 time scales was still on its way after four, "0.83 of its step"), the
    noise's σ taken off in quadrature (PV units)."""
    n = max(3, scale_samples)
    k = y.size // n
    if k == 0:
        return []
    rows = y[: k * n].reshape(k, n)
    x = np.arange(n) - 0.5 * (n - 1)
    dev = rows - rows.mean(axis=1, keepdims=True)
    dev = dev - np.outer(dev @ x / (x @ x), x)
    power = np.mean(dev**2, axis=1) - noise**2
    return [math.sqrt(max(float(p), 0.0)) for p in power]


def judge(y: np.ndarray, step: float, noise: float, scale_samples: int) -> MarginCheck:
    """The check of record ``y`` (PV units, from the check's setpoint step on), after a step
    of ``step``, noise σ ``noise``, time scales of ``scale_samples`` samples."""
    size = abs(step)
    rms = swings_of(y, noise, scale_samples)
    if not rms or size <= 0:
        return MarginCheck(None, None)
    last = rms[-1] / size
    before = rms[1:-1]
    growth = None
    # read only where the last swing stands clear of the noise (its RMS past σ): a swing that
    # small is the noise's own, less an estimate of it, and its ratios mean nothing
    if before and rms[-1] > noise:
        # over a least one within the noise (none of it left), as over a tenth of σ: finite,
        # as a message carries it (a mode growing out of the noise reads large, as it is)
        floor = max(0.1 * noise, 1e-12 * size)
        growth = rms[-1] / max(min(before), floor)
    return MarginCheck(last, growth)


def problem(
    check: MarginCheck,
    factor: float = FACTOR,
    derivative: bool = True,
    predicted: float | None = None,
) -> str | None:
    """Why gains fail the check (None: they pass); ``derivative``: the gains have one (a PI's
    check, made only for a fast mode it rang with, has no derivative to blame); ``predicted``:
    their gain margin on the process model (None: not predicted). A model that predicts a
    margin under ``factor`` itself explains the failure: no mode beyond the test is blamed (an
    FOPDT's TL PID, admitted past Ms 2 by --ms-bound 3, was said to meet "a resonance?")."""
    if not check.failed:
        return None
    if check.stopped is not None:
        swung = check.stopped.startswith("swung")
        seen = check.stopped if swung else f"was cut short: {check.stopped}"
    elif check.mode_grows:
        seen = (
            f"rang on at {check.mode_period:.3g} s, {check.mode:.2f} of its amplitude kept "
            "each period (growing), the fast mode these gains left ringing"
        )
    elif check.swing is not None and check.swing > LASTING:
        seen = f"kept swinging, {check.swing:.2f} of its step (RMS) over the last time scale"
    else:
        seen = (
            f"swung more and more, {check.swing:.2f} of its step (RMS) over the last time "
            f"scale, {check.growth:.2g} times the least before"
        )
    if predicted is not None and predicted < factor and not check.mode_grows:
        why = (
            f"As the process model predicts: it gives these gains a gain margin of "
            f"{predicted:.3g}, so Kc × {factor:.3g} is past the loop's ultimate gain: a more "
            "robust rule (--rule), not forced"
        )
        return (
            f"gain margin under {factor:.3g}: with Kc × {factor:.3g} (Ti and Td kept) the loop "
            f"{seen}. {why}"
        )
    why = (
        # a mode the gains rang with, PI or PID, or a PI's check cut short: the loop's gain at
        # the mode is what is too high (a PI has no derivative to blame)
        "A mode of the process beyond the test's frequency (a resonance) where the loop's "
        "gain is too high for it: a lower Kc, or the mode filtered from the loop"
        if (check.mode_grows and check.stopped is None) or not derivative
        else "A mode of the process beyond the test's frequency (a resonance?) that the "
        "derivative's gain reaches: a PI rule (--rule), or the mode filtered from the loop"
    )
    return (
        f"gain margin under {factor:.3g}: with Kc × {factor:.3g} (Ti and Td kept) the loop "
        f"{seen}; gains within Ms ≤ {admitted_ms(factor):.3g} keep a margin of {factor:.3g} or "
        f"more. {why}"
    )
