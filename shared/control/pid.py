"""The loop's PID block, as in a DCS: ideal (ISA) form, derivative filter, manual/auto,
bumpless transfer and gain changes, output limits with anti-windup.

Discretisation (Åström & Hägglund, *Advanced PID Control*, 2006, §3.6; *Computer-Controlled
Systems*, 1997, §8.6), executed once per sample period T at t_k, s = +1 reverse, −1 direct:

    P_k = s·Kc·(β·sp_k − y_k)
    D_k = −s·Kc·Td·ẏ_k,  ẏ_k = Tf/(Tf+T)·ẏ_{k−1} + (y_k − y_{k−1})/(Tf+T),  Tf = Td/N
    u_k = clamp(P_k + I_k + D_k, lo, hi)
    I_{k+1} = I_k + s·Kc·T/Ti·(sp_k − y_k)

Derivative acts on the measurement (no kick on setpoint changes), backward difference (stable
for any Td, T). The integral term I is kept in output units, so bumpless transfer sets it
to u − P − D on a switch to auto or a gain change. Anti-windup is conditional integration:
the integrator holds while the output sits at a limit and the error would drive it further,
and the output at zero error (I, plus P's setpoint term s·Kc·(β − 1)·sp where β < 1) stays
within the output limits; so the output leaves a limit as soon as the error reverses. With
Ti = None the I term is a manual reset (bias), still set bumplessly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

Mode = Literal["manual", "auto"]
Action = Literal["reverse", "direct"]  # reverse: the output falls as the PV rises


@dataclass(frozen=True)
class PidSettings:
    """The block's tuning: gains in ideal (ISA) form, derivative filter and setpoint weight.

    ``kc`` % of output per PV unit; ``ti`` integral time in s (None: no integral action, P or
    PD with a manual reset); ``td`` derivative time in s; ``n`` the derivative filter, Tf =
    Td/n (1–1000); ``beta`` the setpoint weight on P action (0–1). The same bounds as the bus
    message ``shared.messages.PidGains``, which converts to and from this at the edge.
    """

    kc: float
    ti: float | None = None
    td: float = 0.0
    n: float = 10.0
    beta: float = 1.0

    def __post_init__(self) -> None:
        values = (self.kc, self.td, self.n, self.beta) + (() if self.ti is None else (self.ti,))
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"PID settings must be finite numbers, got {self}")
        if self.kc < 0:
            raise ValueError(f"kc must be ≥ 0 % per PV unit, got {self.kc}")
        if self.ti is not None and not self.ti > 0:
            raise ValueError(f"ti must be > 0 s or None, got {self.ti}")
        if self.td < 0:
            raise ValueError(f"td must be ≥ 0 s, got {self.td}")
        if not 1.0 <= self.n <= 1000.0:
            raise ValueError(f"n must lie in [1, 1000], got {self.n}")
        if not 0.0 <= self.beta <= 1.0:
            raise ValueError(f"beta must lie in [0, 1], got {self.beta}")


@dataclass
class PidTerms:
    """The last execution's terms, in % of output."""

    p: float = 0.0
    i: float = 0.0
    d: float = 0.0


class PidBlock:
    """One PID block; call ``update(sp, pv)`` once per sample period."""

    def __init__(
        self,
        gains: PidSettings,
        sample_time: float,
        op_limits: tuple[float, float],
        action: Action = "reverse",
        mode: Mode = "manual",
        op: float = 0.0,
    ):
        lo, hi = op_limits
        if not 0.0 <= lo < hi <= 100.0:
            raise ValueError(f"op_limits must satisfy 0 ≤ low < high ≤ 100, got {op_limits}")
        if sample_time <= 0:
            raise ValueError(f"sample_time must be > 0, got {sample_time}")
        self.gains = gains
        self.sample_time = sample_time
        self.op_limits = (float(lo), float(hi))
        self.sign = 1.0 if action == "reverse" else -1.0
        self.action: Action = action
        self.mode: Mode = mode
        self.op = self._clamp(op)
        self.terms = PidTerms(i=self.op)
        self._pv_prev: float | None = None
        self._dpv = 0.0  # filtered d(pv)/dt, PV units per s

    def _clamp(self, u: float) -> float:
        lo, hi = self.op_limits
        return min(max(u, lo), hi)

    def _p(self, sp: float, pv: float) -> float:
        return self.sign * self.gains.kc * (self.gains.beta * sp - pv)

    def _d(self) -> float:
        return -self.sign * self.gains.kc * self.gains.td * self._dpv

    def _filter_derivative(self, pv: float) -> None:
        if self._pv_prev is None:
            self._dpv = 0.0
        else:
            tf = self.gains.td / self.gains.n
            t = self.sample_time
            self._dpv = tf / (tf + t) * self._dpv + (pv - self._pv_prev) / (tf + t)
        self._pv_prev = pv

    def track(self, pv: float, op: float) -> None:
        """Manual mode: follow the process so a later switch to auto is bumpless."""
        self._filter_derivative(pv)
        self.op = self._clamp(op)

    def update(self, sp: float, pv: float) -> float:
        """Auto mode: execute once at t_k; return the output to hold until t_{k+1}."""
        self._filter_derivative(pv)
        p, d = self._p(sp, pv), self._d()
        i = self.terms.i
        v = p + i + d
        u = self._clamp(v)
        self.terms = PidTerms(p, i, d)
        self.op = u
        if self.gains.ti is not None:
            step = self.sign * self.gains.kc * self.sample_time / self.gains.ti * (sp - pv)
            lo, hi = self.op_limits
            winding_up = (v >= hi and step > 0) or (v <= lo and step < 0)
            if not winding_up:
                # the output at zero error, I + P(sp = pv), may not grow past a limit, but a
                # bumpless rebase may have left it outside one: it is never pulled back in a
                # jump. (With β < 1, P at zero error is s·Kc·(β − 1)·sp, and I holds it off:
                # bounding I alone by the limits froze the integral of a weighted loop.)
                off = self.sign * self.gains.kc * (self.gains.beta - 1.0) * sp
                i_next = i + step
                if step > 0 and i_next > hi - off:
                    i_next = max(i, hi - off)
                elif step < 0 and i_next < lo - off:
                    i_next = min(i, lo - off)
                self.terms.i = i_next
        return u

    def _rebase(self, sp: float, pv: float) -> None:
        """Set I so that P + I + D equals the present output (bumpless)."""
        p, d = self._p(sp, pv), self._d()
        self.terms = PidTerms(p, self.op - p - d, d)

    def set_mode(self, mode: Mode, sp: float, pv: float) -> None:
        """Switch mode at the present output; to auto, without a bump."""
        if mode == "auto" and self.mode != "auto":
            self._rebase(sp, pv)
        self.mode = mode

    def set_gains(self, gains: PidSettings, sp: float, pv: float) -> None:
        """Change gains without moving the output. The D term goes on from the value it had
        (the new filter's state set to give it), so that only the change of P is taken into I:
        recomputed from the old filter's rate (with Td = 0, the raw difference of the last
        two samples, the noise's), Kc·Td times it went into I, and the output moved by as much
        as the new filter forgot it (Td 0 → 5 s on hx1's noise: up to 11.5 %). Turning the
        derivative off leaves its last value in I, as any bumpless switch must."""
        d = self._d()
        self.gains = gains
        if gains.td > 0 and gains.kc > 0:
            self._dpv = -d / (self.sign * gains.kc * gains.td)
        self._rebase(sp, pv)

    def set_output(self, op: float) -> None:
        """Manual output (the caller refuses it in auto)."""
        self.op = self._clamp(op)
