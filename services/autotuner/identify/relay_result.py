"""What a relay test found: K_u, P_u, the exact frequency points and the model, as the
rules need them (``identification``) and as the run's ``experiment`` object (``to_dict``)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from services.autotuner.identify import inverse_response
from services.autotuner.identify.experiments import Identification
from services.autotuner.identify.fourier import FrequencyPoint
from services.autotuner.identify.model_fit import ProcessFit
from services.autotuner.identify.relay_estimate import MODEL_CROSSING


@dataclass(frozen=True)
class RelayResult:
    ku: float
    pu: float
    amplitude: float  # a, PV units (mean over the agreeing cycles)
    relay_amplitude: float  # d, % (at the end: it may have grown, ``RelayConfig.grow_times``)
    hysteresis: float  # ε, PV units
    bias: float  # b at the end, %
    noise_std: float
    cycles: int  # how many cycles were run
    ku_spread: float  # (max − min)/mean over the agreeing cycles
    pu_spread: float
    rest_pv: float  # r
    frequency: tuple[FrequencyPoint, ...] = ()  # G(jkω), k = 1, 3, 5 (fourier module)
    ku_df: float = math.nan  # the describing-function estimate of stage 1
    pu_df: float = math.nan
    stage_one_cycles: int = 0
    # the whole periods stage 1's frequency points were read over (its window: the last
    # agreeing cycles, not every cycle run); 0: not known
    stage_one_periods: int = 0
    second: tuple[FrequencyPoint, ...] = ()  # stage 2's exact G(jkω₂), k = 1, 2, 3
    # the process gain of the model fitted on a record with stage 2's bias (None: no bias);
    # the bias's step in the mean output is what pins it (the DC ratio of two short stages is
    # not yet settled)
    static_gain: float | None = None
    model: ProcessFit | None = None  # fitted to both stages' points (model_fit)
    # how K_u and P_u were found: "bracketed" (the stages' points lie on both sides of
    # −180°), "near" (a point within near_deg of it: a short interpolation), or "not reached"
    # (both far from it: ku/pu are then the model's own ultimate point, NaN without a model)
    crossing: str = "bracketed"
    phase_reached_deg: float = -180.0  # the measured phase closest to −180°
    cycle_period: float = math.nan  # s, stage 1's mean period
    ku_method: str = MODEL_CROSSING  # which path produced K_u (relay_estimate.KU_METHODS)
    sample_time: float = math.nan  # s (for what is said of a cycle short of −180°)
    # how far the PV first went the other way in the first push (PV units): an inverse
    # response (``RelayTest._inverse_dip``); None when it did not
    inverse_dip: float | None = None
    # d at the start where it grew (%; None: it did not)
    relay_amplitude_start: float | None = None
    # what held d where the cycle still rode on the hysteresis (None: nothing did)
    relay_growth_held: str | None = None
    # degrees by which stage 2's and stage 1's points contradict a phase falling with
    # frequency (``relay_estimate.order_contradiction``; None: they agree); the spreads are
    # then stage 1's alone
    order_contradiction: float | None = None

    @property
    def measured(self) -> bool:
        """K_u and P_u were measured (the cycles ran near enough −180°)."""
        return self.crossing != "not reached"

    def to_dict(self) -> dict[str, Any]:
        """The run's ``experiment`` object (its keys are part of the JSON interface)."""
        return {
            "crossing": self.crossing,
            "ku_method": self.ku_method,
            "phase_reached_deg": self.phase_reached_deg,
            **({} if self.measured else {"ku_model": self.ku, "pu_model": self.pu}),
            "relay_amplitude": self.relay_amplitude,
            **(
                {"relay_amplitude_start": self.relay_amplitude_start}
                if self.relay_amplitude_start is not None
                else {}
            ),
            **(
                {"relay_growth_held": self.relay_growth_held}
                if self.relay_growth_held is not None
                else {}
            ),
            "amplitude": self.amplitude,
            "hysteresis": self.hysteresis,
            "bias": self.bias,
            "cycles": self.cycles,
            "noise_std": self.noise_std,
            "rest_pv": self.rest_pv,
            "ku_describing_function": self.ku_df,
            "pu_describing_function": self.pu_df,
            "stage_one_cycles": self.stage_one_cycles,
            "stage_one_periods": self.stage_one_periods,
            **frequency_fields(self.frequency, self._noise_share(self.stage_one_periods)),
            **{
                f"stage2_{k}": v
                for k, v in frequency_fields(self.second, self._noise_share(1)).items()
            },
            **(self.model.to_dict() if self.model else {}),
            **({"static_gain": self.static_gain} if self.static_gain is not None else {}),
            **({"inverse_dip": self.inverse_dip} if self.inverse_dip is not None else {}),
        }

    def _noise_share(self, periods: int) -> tuple[float, float, float, float] | None:
        """(σ, the sample time, the window in periods, d) for ``harmonic_noise`` of a stage's
        points over ``periods`` whole periods; None where a figure is missing."""
        figures = (self.noise_std, self.sample_time, float(periods), self.relay_amplitude)
        if not all(math.isfinite(x) and x > 0 for x in figures[1:]) or not self.noise_std >= 0:
            return None
        return figures

    def _why_short(self) -> str:
        """What kept the cycle short of −180°, and what would help: the hysteresis the noise
        needs (its lag asin(ε/a)), and the sampling (a switch lands up to a sample late:
        360° over the samples a period)."""
        short = 180.0 + self.phase_reached_deg
        lag = _short_of(self.hysteresis, self.amplitude)
        per_sample = 360.0 * self.sample_time / self.cycle_period
        causes = []
        if lag >= 0.25 * short:
            causes.append(
                f"the hysteresis the noise needs, {self.hysteresis:.3g}, is "
                f"{self.hysteresis / self.amplitude:.0%} of the cycle's amplitude, "
                f"{lag:.0f}° of lag ({self._growth()})"
            )
        if math.isfinite(per_sample) and per_sample >= 0.25 * short:
            causes.append(
                f"the cycle has {self.cycle_period / self.sample_time:.3g} samples a period, "
                f"and a switch lands up to a sample ({per_sample:.0f}°) late (a shorter "
                "sample time resolves it)"
            )
        return "; ".join(causes) or (
            f"the relay's own lag: its hysteresis gives {lag:.0f}° of the {short:.0f}°"
        )

    def _growth(self) -> str:
        """What the relay's amplitude did about a cycle riding on the hysteresis."""
        grew = (
            f"d grew from {self.relay_amplitude_start:g} % to {self.relay_amplitude:.3g} %"
            if self.relay_amplitude_start is not None
            else f"d stayed at {self.relay_amplitude:g} %"
        )
        if self.relay_growth_held is not None:
            return f"{grew}, held there by {self.relay_growth_held}"
        if self.relay_amplitude_start is not None:
            return f"{grew} to lift the cycle clear of the noise"
        return "a larger --amplitude lifts the cycle clear of the noise"

    def identification(self) -> Identification:
        measured = self.measured
        notes = []
        if not measured:
            notes.append(
                f"the relay's cycle ran at {self.phase_reached_deg:.0f}°, far from −180° "
                f"({self._why_short()}): K_u and P_u were not measured, so the rules that need "
                "them are not offered"
                + (
                    f"; the model's own ultimate point is K_u ≈ {self.ku:.4g}, "
                    f"P_u ≈ {self.pu:.4g} s"
                    if math.isfinite(self.ku)
                    else ""
                )
            )
        if self.inverse_dip is not None:
            notes.append(
                inverse_response.note("in the relay's first push", self.inverse_dip, self.model)
            )
        if measured and self.order_contradiction is not None and self.second and self.frequency:
            p1, p2 = self.frequency[0], self.second[0]
            notes.append(
                f"the relay's two points contradict each other: at {min(p1.omega, p2.omega):.4g} "
                f"rad/s the phase lags {self.order_contradiction:.0f}° more than at "
                f"{max(p1.omega, p2.omega):.4g} rad/s, which no phase falling with frequency "
                "gives (the noise's?): K_u and P_u are as sure as stage 1's point alone, "
                f"spreads {100 * self.ku_spread:.2g} % and {100 * self.pu_spread:.2g} %"
            )
        return Identification(
            inverse_response=self.inverse_dip is not None,
            static_gain_known=self.static_gain is not None,
            ku=self.ku if measured else None,
            pu=self.pu if measured else None,
            ku_spread=self.ku_spread if measured else None,
            pu_spread=self.pu_spread if measured else None,
            notes=notes,
            experiment=self,
            timescale=self.pu if math.isfinite(self.pu) else self.cycle_period,
            noise=self.noise_std,
            rest_pv=self.rest_pv,
            model=self.model,
        )


def _short_of(hysteresis: float, amplitude: float) -> float:
    """Degrees of lag a relay's hysteresis gives a cycle of this amplitude, asin(ε/a)."""
    return math.degrees(math.asin(min(hysteresis / amplitude, 1.0))) if amplitude > 0 else 90.0


def frequency_fields(
    points: tuple[FrequencyPoint, ...],
    share: tuple[float, float, float, float] | None = None,
) -> dict[str, float]:
    """The frequency points of a relay test, flat for JSON: omega_k (rad/s), g_k_magnitude
    (PV units per %), g_k_phase_deg, k = 1, 3, 5, and, given ``share`` (σ, sample time,
    window in periods, d: ``harmonic_noise``), g_k_noise, the noise's share of each."""
    out: dict[str, float] = {}
    previous = 0.0
    for p in points:
        k = round(p.omega / points[0].omega)
        phase = p.phase_deg
        while phase > previous:  # unwrapped: the lag grows with frequency
            phase -= 360.0
        previous = phase
        out[f"omega_{k}"] = p.omega
        out[f"g_{k}_magnitude"] = p.magnitude
        out[f"g_{k}_phase_deg"] = phase
        if share is not None and p.magnitude > 0:
            sigma, ts, periods, d = share
            window = periods * 2.0 * math.pi / points[0].omega
            out[f"g_{k}_noise"] = harmonic_noise(k, p.magnitude, sigma, ts, window, d)
    return out


def harmonic_noise(
    k: int, magnitude: float, sigma: float, sample_time: float, window: float, d: float
) -> float:
    """The PV noise's share of G(jkω) read over ``window`` s, relative (rms radius of the
    disc about it): white noise of σ sums to σ·√(T·W) in the PV's Fourier component and a
    relay of ±d puts 2dW/(kπ) in the output's, so δ = kπσ·√(T/W)/(2d·|G(jkω)|). A harmonic
    is weak twice over (1/k of the excitation, through a plant that falls off): hx1's 5th
    read 42 % and 35° off its plant, with δ 0.35 (helper trial); its fundamental's is 0.4 %."""
    return k * math.pi * sigma * math.sqrt(sample_time / window) / (2.0 * d * magnitude)
