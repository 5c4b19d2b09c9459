"""The identification benchmark: relay and ramp tunes of a suite of plants, in-process.

Every tune builds its experiment from the registry (``methods.build``) and runs it through
the one driver (``driver.drive``) — the very state machines the live tuner drives over Zenoh,
with the switches its set-up turns on (``experiments.live_flags``) — but against a plant
model stepped in the same process, so hundreds of tunes take seconds.
Each result is compared with the plant's exact ultimate point (the phase crossover of G(jω),
``DelayedTF.ultimate_point``).

Plants follow Åström & Hägglund's test batch (*Advanced PID Control*, 2006, §7.2): first order
plus dead time over L/T, 1/(s+1)ⁿ, (1−αs)/(s+1)³, the four-pole α family, e^{−s}/(1+sT)²
and an integrator with dead time. Noise is white, its σ given as a fraction of the relay's
peak-to-peak PV swing 2a ≈ 8d/(πK_u).

A second table reproduces Iinoya & Hotta (1958) for K·e^{−Ls}/(Ts+1): the measured K₀·R·L
and τ₀/L against their closed form (tan ω₀L = −Tω₀, K₀·K = √(1 + (Tω₀)²), R = K/T), and the
decay ratio that the Ziegler–Nichols P rule (Kc = 0.5K_u) actually gives against its 25 % aim;
it and the paper's three figures live in ``services.offline.iinoya_hotta``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from services.autotuner.design import output_noise
from services.autotuner.design.predicted_response import predicted_setpoint_step
from services.autotuner.design.sampled_loop import sampled_loop_robustness
from services.autotuner.design.selection import select
from services.autotuner.identify import methods
from services.autotuner.identify.driver import drive
from services.autotuner.identify.experiments import Settings, Setup, live_flags
from services.offline.local_loop import ModelPort, SimLoopPort
from services.plant_sim.plant_file import build_plant
from services.plant_sim.simulation.models import TransferFunctionModel
from shared.control.forms import IsaGains
from shared.control.transfer import DelayedTF
from shared.messages import GainsCommand, ModeCommand, PidGains

RELAY_AMPLITUDE = 5.0  # %
SAMPLES_PER_PERIOD = 400  # the sampled loop's ZOH lag stays ≈ 0.5° at the crossover
NOISE_LEVELS = (0.0, 0.01, 0.03)


@dataclass(frozen=True)
class Plant:
    name: str
    family: str
    tf: DelayedTF  # G(s), gain in PV units per %, time in s

    @classmethod
    def of(cls, name: str, family: str, num, den, delay: float) -> Plant:
        return cls(name, family, DelayedTF.of(num, den, delay))

    def exact(self) -> tuple[float, float]:
        up = self.tf.ultimate_point()
        if up is None:
            raise ValueError(f"plant {self.name}: its phase never reaches −180°")
        return up


def _poly(*factors: list[float]) -> tuple[float, ...]:
    out = np.array([1.0])
    for f in factors:
        out = np.polymul(out, f)
    return tuple(float(c) for c in out)


def suite() -> list[Plant]:
    """The benchmark's plants (time in seconds, gains in PV units per %)."""
    plants = [
        Plant.of(f"fopdt L/T={r:g}", "fopdt", (1.0,), (1.0 / r, 1.0), 1.0)
        for r in (0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
    ]
    plants += [
        Plant.of(f"1/(s+1)^{n}", "lag", (1.0,), _poly(*[[1, 1]] * n), 0.0) for n in (3, 4, 8)
    ]
    plants += [
        Plant.of(f"(1-{a:g}s)/(s+1)^3", "nmp", (-a, 1.0), _poly([1, 1], [1, 1], [1, 1]), 0.0)
        for a in (0.1, 0.2, 0.5, 1.0, 2.0)
    ]
    plants += [
        Plant.of(
            f"four-pole a={a:g}",
            "four-pole",
            (1.0,),
            _poly([1, 1], [a, 1], [a**2, 1], [a**3, 1]),
            0.0,
        )
        for a in (0.1, 0.2, 0.5, 1.0)
    ]
    plants += [
        Plant.of(f"e^-s/(1+{t:g}s)^2", "sopdt", (1.0,), _poly([t, 1], [t, 1]), 1.0)
        for t in (0.1, 1.0, 10.0)
    ]
    plants.append(Plant.of("e^-s/s", "integrating", (1.0,), (1.0, 0.0), 1.0))
    return plants


@dataclass(frozen=True)
class TuneOutcome:
    plant: str
    family: str
    method: str
    noise: float
    ku_exact: float
    pu_exact: float
    ok: bool
    reason: str = ""
    ku_error: float = math.nan  # ours, relative
    pu_error: float = math.nan
    ku_df_error: float = math.nan  # the describing function (relay stage 1)
    pu_df_error: float = math.nan
    periods_classic: float = math.nan  # the relay's stage 1, in P_u
    periods: float = math.nan  # the whole experiment, in P_u
    model: str = ""
    recommended: str = ""
    recommended_ms: float = math.nan  # on the true plant's sampled loop
    recommended_stable: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


def _swing(ku: float) -> float:
    return 8.0 * RELAY_AMPLITUDE / (math.pi * ku)


def run_relay(plant: Plant, noise: float, seed: int = 0) -> TuneOutcome:
    ku, pu = plant.exact()
    ts = pu / SAMPLES_PER_PERIOD
    tf = plant.tf
    model = TransferFunctionModel(ts, num=list(tf.num), den=list(tf.den), delay=tf.delay)
    model.reset()
    setup = Setup(
        sample_time=ts,
        op_lo=0.0,
        op_hi=100.0,
        pv_lo=-1e9,
        pv_hi=1e9,
        op_start=50.0,
        direction=1.0,
        **live_flags("relay"),  # the experiment the live tuner runs
    )
    test = methods.build("relay", Settings(), setup)
    sigma = noise * _swing(ku)
    drive(test, ModelPort(model, ts, 50.0, sigma, np.random.default_rng(seed)))
    if test.result is None:
        return _outcome(plant, "relay", noise, test)
    start = next(e.t for e in test.events if e.kind == "relay_start")
    stage = next((e.t for e in test.events if e.kind == "stage"), math.nan)
    done = next(e.t for e in test.events if e.kind == "done")
    return _outcome(
        plant, "relay", noise, test, periods_classic=stage - start, periods=done - start
    )


def run_ramp(plant: Plant, noise: float, seed: int = 0) -> TuneOutcome:
    """The P-gain ramp on the plant's own PID block, from a cautious Kc = 0.3·K_u loop."""
    ku, pu = plant.exact()
    ts = pu / SAMPLES_PER_PERIOD
    a = 0.5 * _swing(ku)
    loop = build_plant(
        {
            "seed": seed,
            "loops": {
                "x": {
                    "model": "transfer_function",
                    "num": list(plant.tf.num),
                    "den": list(plant.tf.den),
                    "delay": plant.tf.delay,
                    "sample_time": ts,
                    "noise_std": noise * 2 * a,
                    "pv_range": [-1e9, 1e9],
                }
            },
        }
    )["x"]
    kc0 = 0.3 * ku
    loop.apply(GainsCommand(loop="x", gains=PidGains(kc=kc0)))
    loop.apply(ModeCommand(loop="x", mode="auto"))
    setup = Setup(
        sample_time=ts,
        op_lo=0.0,
        op_hi=100.0,
        pv_lo=-1e9,
        pv_hi=1e9,
        kc_start=0.5 * kc0,
        bump=a,
        sp_start=loop.sp,
        **live_flags("ramp"),
    )
    test = methods.build("ramp", Settings(), setup)
    t0 = loop.t
    port = SimLoopPort(loop, present_first=True)  # its present state is the first sample
    drive(test, port, held=port.held_now())
    return _outcome(plant, "ramp", noise, test, periods=loop.t - t0)  # s: _outcome divides


def _outcome(plant: Plant, method: str, noise: float, test, **lengths: float) -> TuneOutcome:
    """A finished test's figures against the plant's exact ultimate point."""
    ku, pu = plant.exact()
    base = dict(plant=plant.name, family=plant.family, method=method, noise=noise)
    r = test.result
    if r is None:
        return TuneOutcome(**base, ku_exact=ku, pu_exact=pu, ok=False, reason=test.reason)
    extra = {}
    if method == "relay":
        extra = dict(ku_df_error=r.ku_df / ku - 1.0, pu_df_error=r.pu_df / pu - 1.0)
    return TuneOutcome(
        **base,
        ku_exact=ku,
        pu_exact=pu,
        ok=True,
        ku_error=r.ku / ku - 1.0,
        pu_error=r.pu / pu - 1.0,
        model=r.model.kind if r.model else "",
        **extra,
        **{k: v / pu for k, v in lengths.items()},
        **_recommendation(plant, test),
    )


def _recommendation(plant: Plant, test) -> dict:
    """The recommended rule's gains, chosen as live (``selection.select`` with rule auto at the
    loop's sample time: the model checked, the candidates judged on the sampled loop), judged
    on the true plant's sampled loop: Ms and stability. None recommended: empty."""
    ident = test.identification()
    if ident is None:
        return {}
    ts = plant.exact()[1] / SAMPLES_PER_PERIOD
    sel = select(ident, "auto", sample_time=ts, max_op_noise=output_noise.DEFAULT_LIMIT)
    rec = sel.recommended
    if rec is None or sel.refusal:
        return {}
    rb = sampled_loop_robustness(rec.gains, plant.tf, ts)
    return {
        "recommended": rec.rule,
        "recommended_ms": rb.ms,
        "recommended_stable": bool(rb.stable),
    }


# --- Iinoya & Hotta ------------------------------------------------------------------------
# The section lives in ``services.offline.iinoya_hotta`` (the paper's three figures); its
# names are re-exported here for the code that reads them from the benchmark, imported on
# first use because that module builds on this one.

_IINOYA_HOTTA = ("iinoya_hotta", "IinoyaHottaRow", "iinoya_hotta_row", "IH_RATIOS")


def __getattr__(name: str):
    if name in _IINOYA_HOTTA:
        from services.offline import iinoya_hotta

        return getattr(iinoya_hotta, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def decay_ratio(gains: IsaGains, plant: Plant, pu: float, periods: float = 12.0) -> float:
    """Decay ratio of the closed loop's setpoint response on the exact plant, with the loop's
    own PID block at P_u/2000 (``predicted_setpoint_step``): the second overshoot over the
    first, measured about the final value."""
    return predicted_setpoint_step(
        gains, plant.tf, pu, pu / 2000, periods, int(periods * 2000)
    ).decay_ratio
