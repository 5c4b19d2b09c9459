"""The loop's sensitivity at the measured ultimate point: a floor on Ms that needs no model.

At the ultimate frequency ω_u = 2π/P_u the plant's response is −1/K_u, measured (a relay's
cycle, a ramp's bracket), so any controller's loop there is L(jω_u) = −C(jω_u)/K_u, and
Ms = max_ω 1/|1 + L(jω)| is at least 1/|1 + L(jω_u)| whatever the plant does elsewhere. A model
whose own Ms for the same gains lies clearly below that floor misses the plant, and its other
predictions with it (seen: ZN PI on the underdamped e^{−0.5s}/(s² + 0.4s + 1) by ramp, 1.71
predicted on a fit with four times the dead time and no resonance, where the measured point
alone implies 1.80; 3.14 on the plant).

On the sampled loop the controller is the PID block's own C(e^{jωT}) and the hold adds its
half sample of lag, e^{−jωT/2}: K_u and P_u are the plant's own (``hold_correction``).
Units: K_u in % of output per PV unit, P_u and T in s.
"""

from __future__ import annotations

import cmath
import math

import numpy as np

from services.autotuner.design.rules import UltimatePoint
from services.autotuner.design.sampled_loop import pid_response
from shared.control.forms import IsaGains

DERIVATIVE_FILTER = 10.0  # N of the loop's PID block (Tf = Td/N), as the rules' gains get it


def ms_floor(gains: IsaGains, ultimate: UltimatePoint, sample_time: float | None) -> float:
    """1/|1 + L(jω_u)|: the least Ms the loop can have with these gains, from K_u and P_u
    alone (inf where L(jω_u) = −1: the loop oscillates at ω_u)."""
    w = 2.0 * math.pi / ultimate.pu
    if sample_time:
        z = np.array([cmath.exp(1j * w * sample_time)])
        c = complex(pid_response(gains, sample_time, z, DERIVATIVE_FILTER)[0])
        c *= cmath.exp(-0.5j * w * sample_time)  # the hold's half sample
    else:
        c = gains.kc * (
            1.0
            + (1.0 / (1j * w * gains.ti) if gains.ti is not None else 0.0)
            + 1j * w * gains.td / (1.0 + 1j * w * gains.td / DERIVATIVE_FILTER)
        )
    d = abs(1.0 - c / ultimate.ku)
    return math.inf if d == 0.0 else 1.0 / d
