"""The process model of a relay test, identified on its record.

Two uses: the leakage correction of the stages' Fourier points (a window that is not a
steady cycle leaks; the model, simulated over the same output record, leaks alike), and the
model the rules and the robustness figures use (each model fitted to the points, refined on
the whole record from rest, the best by its information criterion).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from services.autotuner.identify.fourier import FrequencyPoint, frequency_points
from services.autotuner.identify.model_fit import (
    ProcessFit,
    choose,
    choose_on_record,
    refine_on_record,
    response_to,
)
from services.autotuner.identify.relay_estimate import Corrector, Points


@dataclass(frozen=True)
class RelayRecord:
    """The test's record: times (s), PV (PV units), output held from each sample (%), from
    the start of the quiet period; and the rest the test started from."""

    t: np.ndarray
    pv: np.ndarray
    op: np.ndarray
    sample_time: float  # s
    op_start: float  # %, the output at rest
    rest_pv: float  # PV units
    noise: float  # σ of the PV at rest


def corrector(
    record: RelayRecord,
    first_window: tuple[float, float, int],
    second_window: tuple[float, float, int] | None,
    second_harmonics: tuple[int, ...],
) -> Corrector:
    """Remove what the window's non-periodicity leaks into the Fourier points.

    Over a window that is not a steady cycle (stage 2's second period still carries the
    change of stage), Y/U ≠ G(jω). The model, simulated over the same output record from
    the same rest, leaks in nearly the same way; so G ≈ M(jω) + (Y − Ŷ)/U, which is exact
    for a perfect model and leaves only the model's error times the (small) leakage. Each
    corrected point carries that error as its ``leak`` (``_rise``): the spreads state it."""
    t, op = record.t, record.op

    def correct(model: ProcessFit) -> tuple[Points, Points]:
        try:
            y_hat = response_to(model, record.sample_time, op - record.op_start)
        except (ValueError, np.linalg.LinAlgError):
            return (), ()
        residual = record.pv - y_hat

        def points(window: tuple[float, float, int], harmonics: tuple[int, ...]) -> Points:
            start, period, n = window
            rise = _rise(t, residual, window, record.noise)
            try:
                found = frequency_points(t, residual, op, start, period, n, harmonics)
                # the leakage of a unit rise, per harmonic (the rise's is proportional)
                unit = frequency_points(t, _ramp(t, window), op, start, period, n, harmonics)
            except ValueError:
                return ()
            out = []
            for p, d in zip(found, unit, strict=True):
                g = p.g + complex(model.response(p.omega))
                out.append(FrequencyPoint(p.omega, g, rise * abs(d.g) / abs(g) if g else math.inf))
            return tuple(out)

        first = points(first_window, (1, 3, 5))
        later = points(second_window, second_harmonics) if second_window else ()
        return first, later

    return correct


def _rise(
    t: np.ndarray, residual: np.ndarray, window: tuple[float, float, int], noise: float
) -> float:
    """How far the residual rises over the window, beyond what the PV's noise ``noise`` (σ)
    makes of the reading. The PV is back where it was at the window's end (the window runs
    between its crossings of the rest), so the rise is the model's own leakage left in the
    correction: not periodic over the window, its Fourier component is the error the
    correction leaves, to first order (i·Δr/(π·n) over n periods for a straight rise). Read as
    the difference of the residual's means over the eighth of a period before the window's
    start and before its end (the same phase of the cycle, so what is periodic cancels), less
    the noise of those means in quadrature."""
    start, period, n = window
    end = start + n * period
    h = period / 8.0
    at_start = (t > start - h) & (t <= start)
    at_end = (t > end - h) & (t <= end)
    if not (at_start.any() and at_end.any()):  # a window at the record's start
        return abs(float(np.interp(end, t, residual) - np.interp(start, t, residual)))
    rise = float(np.mean(residual[at_end]) - np.mean(residual[at_start]))
    read = noise**2 * (1.0 / np.count_nonzero(at_start) + 1.0 / np.count_nonzero(at_end))
    return math.sqrt(max(rise**2 - read, 0.0))


def _ramp(t: np.ndarray, window: tuple[float, float, int]) -> np.ndarray:
    """A unit rise over the window, straight, from 0 at its start."""
    start, period, n = window
    return (t - start) / (n * period)


def process_model(
    record: RelayRecord, candidates: tuple[ProcessFit, ...], offset: bool = False
) -> ProcessFit | None:
    """The process model for rules and robustness: each model fitted to the frequency
    points, refined on the whole record from rest (which adds the slow response and the
    static gain), the best by its information criterion. ``offset``: an integrating model
    also fits the held output's offset from its balance (``refine_on_record``)."""
    y = record.pv - record.rest_pv
    u = record.op[: y.size] - record.op_start
    refined = [
        f
        for start in candidates
        if (f := refine_on_record(start, record.sample_time, u, y, offset and start.kind == "ipdt"))
        is not None
    ]
    best = choose_on_record(refined, y.size)
    if best is None:
        return choose(candidates)
    return dataclasses.replace(best, noise_rms=record.noise / (float(np.std(y)) or 1.0))
