"""Random field cases for the safety property test: plants of the benchmark families, noise,
starting states and methods, each run as a whole live run (``TuningRun``) in-process, and the
applied gains judged on the true plant by an independent oracle.

The oracle is written here from first principles, not taken from the product: the plant's
zero-order-hold discretisation with its fractional dead time (two input matrices), the PID
block's difference equations as ``plant_sim.pid`` documents them, and the closed loop's
state matrix; stability is its spectral radius, Ms the peak of |1/(1 + L(e^{jωT}))|.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm
from scipy.signal import tf2ss

from tests.exact import ultimate_point

RELAY_D = 5.0  # %: the relay's default amplitude, for the noise scale


@dataclass(frozen=True)
class Case:
    index: int
    family: str
    num: tuple[float, ...]
    den: tuple[float, ...]
    delay: float
    sample_time: float
    noise: float  # PV units
    start: str  # "rest", "drifting", "after step"
    method: str
    seed: int
    ku: float  # the continuous plant's exact ultimate point
    pu: float


def _poly(*factors: list[float]) -> tuple[float, ...]:
    out = np.array([1.0])
    for f in factors:
        out = np.polymul(out, f)
    return tuple(float(c) for c in out)


def random_case(index: int, seed: int = 10) -> Case:
    rng = np.random.default_rng([seed, index])
    family = str(rng.choice(["fopdt", "lag", "nmp", "four-pole", "sopdt", "integrating"]))
    scale = float(np.exp(rng.uniform(math.log(0.5), math.log(20.0))))  # s per unit time
    if family == "fopdt":
        ratio = float(np.exp(rng.uniform(math.log(0.05), math.log(10.0))))  # L/T
        num, den, delay = (1.0,), (scale / ratio, 1.0), scale
    elif family == "lag":
        n = int(rng.choice([3, 4, 8]))
        num, den, delay = (1.0,), _poly(*[[scale, 1.0]] * n), 0.0
    elif family == "nmp":
        a = float(rng.uniform(0.1, 2.0))
        num, den, delay = (-a * scale, 1.0), _poly(*[[scale, 1.0]] * 3), 0.0
    elif family == "four-pole":
        a = float(rng.uniform(0.1, 1.0))
        num = (1.0,)
        den = _poly(*[[scale * a**k, 1.0] for k in range(4)])
        delay = 0.0
    elif family == "sopdt":
        t = float(np.exp(rng.uniform(math.log(0.1), math.log(10.0))))
        num, den, delay = (1.0,), _poly([scale * t, 1.0], [scale * t, 1.0]), scale
    else:
        num, den, delay = (1.0 / scale,), (1.0, 0.0), scale
    gain = float(np.exp(rng.uniform(math.log(0.3), math.log(3.0))))
    num = tuple(gain * c for c in num)
    ku, pu = ultimate_point(list(num), list(den), delay)
    samples = float(np.exp(rng.uniform(math.log(15.0), math.log(100.0))))  # per period
    swing = 8.0 * RELAY_D / (math.pi * ku)
    noise = float(rng.uniform(0.0, 0.03)) * swing
    start = str(rng.choice(["rest", "drifting", "after step"]))
    method = str(rng.choice(["relay", "relay", "ramp", "step"]))
    return Case(index, family, num, den, delay, pu / samples, noise, start, method, index, ku, pu)


def discrete_plant(case: Case) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """(Φ, Γ_now, Γ_late, C, n): x[k+1] = Φx[k] + Γ_now·u[k−n] + Γ_late·u[k−n−1], y = Cx."""
    a, b, c, d = tf2ss(list(case.num), list(case.den))
    assert abs(float(np.asarray(d).item())) < 1e-12, "the families are strictly proper"
    ts = case.sample_time
    n = math.floor(case.delay / ts + 1e-9)
    f = case.delay - n * ts
    if f < 1e-9 * ts:
        f = 0.0

    def zoh(tau: float) -> tuple[np.ndarray, np.ndarray]:
        nx = a.shape[0]
        m = np.zeros((nx + 1, nx + 1))
        m[:nx, :nx], m[:nx, nx:] = a, b
        e = expm(m * tau)
        return e[:nx, :nx], e[:nx, nx:]

    phi, _ = zoh(ts)
    e_late, g_now = zoh(ts - f)
    _, g_early = zoh(f)
    return phi, g_now, e_late @ g_early, c, n


def loop_matrix(case: Case, kc: float, ti: float | None, td: float, n_filter: float = 10.0):
    """The closed loop's state matrix: plant, delay line of outputs, integrator, derivative
    filter (the PID block of plant_sim.pid, reverse acting, setpoint fixed)."""
    phi, g_now, g_late, c, n = discrete_plant(case)
    ts = case.sample_time
    nx = phi.shape[0]
    tf = td / n_filter
    alpha = tf / (tf + ts) if td > 0 else 0.0
    beta = 1.0 / (tf + ts) if td > 0 else 0.0
    ki = kc * ts / ti if ti else 0.0
    # state: x (nx), u[k−1] … u[k−n−1] (n+1), I, ẏ[k−1], y[k−1]
    size = nx + n + 1 + 3
    i_int, i_dy, i_y = nx + n + 1, nx + n + 2, nx + n + 3
    m = np.zeros((size, size))
    # y_k = C x_k; ẏ_k = α ẏ_{k−1} + β (y_k − y_{k−1}); u_k = −Kc y_k + I_k − Kc Td ẏ_k
    y_row = np.zeros(size)
    y_row[:nx] = c[0]
    dy_row = alpha * np.eye(size)[i_dy] + beta * (y_row - np.eye(size)[i_y])
    u_row = -kc * y_row + np.eye(size)[i_int] - kc * td * dy_row
    delayed = [u_row] + [np.eye(size)[nx + j] for j in range(n + 1)]  # u_k, u_{k−1}, …
    m[:nx] = phi @ np.eye(size)[:nx] if nx else 0.0
    m[:nx] += np.outer(g_now[:, 0], delayed[n]) + np.outer(g_late[:, 0], delayed[n + 1])
    m[nx] = u_row  # the line shifts: new u[k−1] is u_k
    for j in range(1, n + 1):
        m[nx + j] = np.eye(size)[nx + j - 1]
    m[i_int] = np.eye(size)[i_int] - ki * y_row
    m[i_dy] = dy_row
    m[i_y] = y_row
    if not ti:  # without integral action I is a constant bias, not a state of the loop
        keep = [k for k in range(size) if k != i_int]
        m = m[np.ix_(keep, keep)]
    return m


def true_loop(case: Case, kc: float, ti: float | None, td: float) -> tuple[bool, float]:
    """(stable, Ms) of the sampled loop with these gains on the true plant."""
    radius = float(np.max(np.abs(np.linalg.eigvals(loop_matrix(case, kc, ti, td)))))
    if radius >= 1.0 - 1e-9:
        return False, math.inf
    phi, g_now, g_late, c, n = discrete_plant(case)
    ts = case.sample_time
    w = np.concatenate(
        (
            np.logspace(math.log10(1e-4 / case.pu), math.log10(math.pi / ts), 4000)[:-1],
            [math.pi / ts],
        )
    )
    z = np.exp(1j * w * ts)
    eye = np.eye(phi.shape[0])
    g = np.array(
        [(c @ np.linalg.solve(zk * eye - phi, g_now + g_late / zk)).item() * zk ** (-n) for zk in z]
    )
    tf = td / 10.0
    cz = kc * (1.0 + (ts / (ti * (z - 1.0)) if ti else 0.0))
    if td > 0:
        cz = cz + kc * td * (1.0 - 1.0 / z) / ((tf + ts) * (1.0 - tf / (tf + ts) / z))
    return True, float(np.max(1.0 / np.abs(1.0 + cz * g)))


def build_loop(case: Case):
    """The case's plant as a plant_sim loop (manual at 50 %, with plausible old gains), put
    in its starting state."""
    from services.plant_sim.plant_file import build_plant
    from shared.messages import OutputCommand

    loop = build_plant(
        {
            "seed": case.seed,
            "loops": {
                "x": {
                    "model": "transfer_function",
                    "num": list(case.num),
                    "den": list(case.den),
                    "delay": case.delay,
                    "sample_time": case.sample_time,
                    "noise_std": case.noise,
                    "pid": {"kc": 0.2 * case.ku, "ti": case.pu},
                }
            },
        }
    )["x"]
    rng = np.random.default_rng([case.seed, 7])
    if case.start != "rest":
        size = float(rng.choice([-5.0, 5.0]))
        loop.apply(OutputCommand(loop="x", op=50.0 + size))
        for _ in range(round(float(rng.uniform(0.2, 1.5)) * case.pu / case.sample_time)):
            loop.advance()
        if case.start == "after step":
            loop.apply(OutputCommand(loop="x", op=50.0))
    return loop


def run_case(case: Case) -> dict:
    """One whole run on the case; what it applied, judged on the true plant."""
    from services.autotuner.tuning import TuningRun
    from services.offline.local_loop import LocalLoopClient
    from shared.messages import TuneRequest

    loop = build_loop(case)
    client = LocalLoopClient(loop)
    t0 = loop.t
    result = TuningRun(client, TuneRequest(loop="x", method=case.method), "p").run()
    out = {
        "case": case.index,
        "family": case.family,
        "method": case.method,
        "start": case.start,
        "status": result.status,
        "reason": result.reason,
        "applied": result.applied,
        "periods": (loop.t - t0) / case.pu,
        "samples_per_period": case.pu / case.sample_time,
        "stable": None,
        "ms": None,
        "ku_error": None if result.ku is None else result.ku / case.ku - 1.0,
    }
    if result.applied and result.chosen:
        isa = result.chosen["isa"]
        stable, ms = true_loop(case, isa["kc"], isa["ti"], isa["td"])
        out.update(stable=stable, ms=ms, rule=result.rule)
    return out
