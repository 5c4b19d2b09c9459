"""Named process models and the loop settings each comes with (sample time, noise, tuning).

Linear: ``transfer_function``, ``fopdt``, ``ipdt`` and ``heat_exchanger`` (the heat exchanger
of the lecture notes in seed 002: e^{−5s}/((10s+1)(60s+1)) °C per % steam valve). Physical:
``heat_exchanger_physical``, ``tank_level``, ``tank_level_integrating``, ``flow``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.plant_sim.simulation.models import (
    FirstOrderPlusDeadTime,
    IntegratingPlusDeadTime,
    TransferFunctionModel,
    finite,
)
from services.plant_sim.simulation.physical import (
    FlowLoop,
    HeatExchangerPhysical,
    TankLevel,
    TankLevelPumped,
)
from shared.messages import Action, PidGains


class HeatExchanger(TransferFunctionModel):
    """Steam valve % → outlet temperature °C: gain·e^{−delay·s}/((tau1·s+1)(tau2·s+1)).

    Defaults are the heat exchanger of seed 002 (lecture 16): K = 1 °C/%, τ₁ = 10 s,
    τ₂ = 60 s, 5 s dead time; 60 °C at 40 % valve. Disturbance ``load`` in % of valve.
    """

    pv_units = "degC"
    pv_range = (0.0, 150.0)

    def __init__(
        self,
        sample_time: float,
        gain: float = 1.0,
        tau1: float = 10.0,
        tau2: float = 60.0,
        delay: float = 5.0,
        op0: float = 40.0,
        pv0: float = 60.0,
        sensor_lag: float = 0.0,
    ):
        gain = finite("gain", gain)
        tau1 = finite("tau1", tau1, low=0.0)
        tau2 = finite("tau2", tau2, low=0.0)
        den = list(np.polymul([tau1, 1.0], [tau2, 1.0]))
        names = {"num": "gain", "den": "tau1/tau2"}
        super().__init__(sample_time, [gain], den, delay, op0, pv0, sensor_lag, names=names)


@dataclass(frozen=True)
class LoopDefaults:
    """What a loop on this model gets unless its plant file says otherwise."""

    sample_time: float | None
    noise_std: float
    gains: PidGains
    action: Action = "reverse"


MODELS: dict[str, type] = {
    "transfer_function": TransferFunctionModel,
    "fopdt": FirstOrderPlusDeadTime,
    "ipdt": IntegratingPlusDeadTime,
    "heat_exchanger": HeatExchanger,
    "heat_exchanger_physical": HeatExchangerPhysical,
    "tank_level": TankLevel,
    "tank_level_integrating": TankLevelPumped,
    "flow": FlowLoop,
}

_GENERIC = LoopDefaults(sample_time=None, noise_std=0.0, gains=PidGains(kc=1.0))

DEFAULTS: dict[str, LoopDefaults] = {
    "transfer_function": _GENERIC,
    "fopdt": _GENERIC,
    "ipdt": _GENERIC,
    "heat_exchanger": LoopDefaults(0.25, 0.02, PidGains(kc=2.0, ti=60.0)),
    "heat_exchanger_physical": LoopDefaults(0.25, 0.02, PidGains(kc=2.0, ti=60.0)),
    "tank_level": LoopDefaults(1.0, 0.002, PidGains(kc=20.0, ti=600.0)),
    "tank_level_integrating": LoopDefaults(1.0, 0.002, PidGains(kc=10.0, ti=4000.0)),
    "flow": LoopDefaults(0.1, 0.2, PidGains(kc=0.3, ti=3.0)),
}

# Loop defaults for a user's own model class (named package.module:Class).
CUSTOM_DEFAULTS = _GENERIC
