"""Hägglund's idle index: how sluggishly a loop answers a load disturbance.

T. Hägglund, "Automatic detection of sluggish control loops", Control Engineering Practice 7,
1999. After a load disturbance a well-tuned loop moves its output hard while the PV is still
going the wrong way, then eases it back as the PV returns: the increments of the output u and
of the PV y have opposite signs (reverse action) much of the time. A sluggish loop creeps: u
and y move the same way nearly all the time. Over the time spent on load disturbances,

    I_i = (t_pos − t_neg) / (t_pos + t_neg),

t_pos (t_neg) the time with Δu·Δy > 0 (< 0), the sign turned for a direct-acting loop (whose
process gain is negative). I_i near +1 is sluggish; near 0 or below, well damped or faster.

Only the half-periods the oscillation detector counted as load disturbances are used (their
IAE above the limit), none within T_u of a setpoint change (a setpoint step moves u and y the
same way in any loop). Noise must not decide the signs: the increments are taken on u and y
low-passed twice (two first-order lags, each T_u/2π), and a sample counts only when both
increments stand clear of what the signals' own white noise (``NoiseLevel``) gives the
filtered increments: a slow creep buried in noise is left out rather than read at random.
"""

from __future__ import annotations

import math

from services.autotuner.monitor.oscillation import GAP_SAMPLES, HalfPeriod, NoiseLevel

FILTER_PERIODS = 1.0 / (2.0 * math.pi)  # each low-pass's time constant, × T_u
NOISE_GATE = 1.0  # an increment counts beyond this many σ of its noise
SLUGGISH_LIMIT = 0.4  # an idle index above this is sluggish (Hägglund 1999)
MIN_PERIODS = 1.0  # load-disturbance time needed before the index is given, × T_u


def increment_gain(alpha: float) -> float:
    """σ of the increment of white noise (σ = 1) through two first-order lags of coefficient
    ``alpha``: √Σh², h the impulse response of Δ∘lag∘lag, summed until it has died out."""
    y1 = y2 = 0.0
    total = 0.0
    x = 1.0
    for _ in range(max(10, math.ceil(40.0 / alpha))):
        y1 += alpha * (x - y1)
        d = alpha * (y1 - y2)
        y2 += d
        total += d * d
        x = 0.0
    return math.sqrt(total)


class IdleIndex:
    """Fed every sample in auto; told by ``close`` which stretches were load disturbances.
    ``sign``: +1 for a reverse-acting loop (positive process gain), −1 for direct."""

    def __init__(self, period: float, sample_time: float, sign: float = 1.0):
        self.period = period
        self.sample_time = sample_time
        self.sign = 1.0 if sign >= 0 else -1.0
        self.t_pos = 0.0  # s with Δu·Δy (signed) > 0, over the kept load disturbances
        self.t_neg = 0.0
        self.u_noise, self.y_noise = NoiseLevel(), NoiseLevel()
        alpha = 1.0 - math.exp(-sample_time / (FILTER_PERIODS * period))
        self._gain = increment_gain(alpha)
        self._pending: list[tuple[float, float]] = []  # (t, ±dt) not yet judged
        self.interrupt()

    def interrupt(self) -> None:
        """Samples missing or the loop out of auto: the filters start again."""
        self._t: float | None = None
        self._u = self._y = self._u1 = self._y1 = 0.0
        self.u_noise.restart()
        self.y_noise.restart()

    def reset(self) -> None:
        """A new report window: the times start from zero (what is pending stays)."""
        self.t_pos = self.t_neg = 0.0

    def feed(self, t: float, op: float, pv: float) -> None:
        if self._t is not None and not 0 < t - self._t <= GAP_SAMPLES * self.sample_time:
            self.interrupt()
        self.u_noise.feed(op)
        self.y_noise.feed(pv)
        if self._t is None:
            self._t, self._u, self._y, self._u1, self._y1 = t, op, pv, op, pv
            return
        dt = t - self._t
        a = 1.0 - math.exp(-dt / (FILTER_PERIODS * self.period))
        self._u1 += a * (op - self._u1)
        self._y1 += a * (pv - self._y1)
        du, dy = a * (self._u1 - self._u), a * (self._y1 - self._y)
        self._t, self._u, self._y = t, self._u + du, self._y + dy
        if (
            abs(du) <= NOISE_GATE * self._gain * self.u_noise.sigma
            or abs(dy) <= NOISE_GATE * self._gain * self.y_noise.sigma
        ):
            return
        product = self.sign * du * dy
        if product != 0.0:
            self._pending.append((t, dt if product > 0 else -dt))

    def close(self, half: HalfPeriod, keep: bool) -> None:
        """The detector closed ``half``: its samples count if ``keep`` (a load disturbance
        clear of setpoint changes); those up to its end are judged, the rest wait."""
        n = 0
        for t, signed in self._pending:
            if t > half.end:
                break
            n += 1
            if keep and t >= half.start:
                if signed > 0:
                    self.t_pos += signed
                else:
                    self.t_neg -= signed
        del self._pending[:n]

    def seconds(self) -> float:
        """Load-disturbance time the index is over (increments clear of noise), s."""
        return self.t_pos + self.t_neg

    def value(self) -> float | None:
        """I_i in [−1, 1]; None with less than MIN_PERIODS·T_u behind it."""
        total = self.seconds()
        if total < MIN_PERIODS * self.period or total <= 0:
            return None
        return (self.t_pos - self.t_neg) / total
