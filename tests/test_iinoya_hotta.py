"""Iinoya & Hotta's three figures (seed 004): the module's solutions of eqs. 5, 7, 12 and 15
against independent ones computed here, and the measured points of the product's experiments.

The independent solutions start from the characteristic equation itself, not from the paper's
rearranged forms. With L = 1, T = r, M = 1 and s on the 25 % ray s = ω(−σ + i), σ = ln 4/(2π),
the setting sought (K for P, T_I for PI at K = 0.9·r, T_D for PD at K = 1.2·r) enters the
characteristic equation linearly, so it is the complex number that solves it at s; a 25 % pair
is where that number is real and positive: the imaginary part's sign changes on a grid of ω,
refined by brentq (poles, where the number runs off to infinity, are dropped). The ultimate
point is ``tests.exact.ultimate_point``, the unwrapped phase crossover.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.optimize import brentq

from services.cli import main
from services.offline import iinoya_hotta as ih
from tests.exact import ultimate_point

SIGMA = math.log(4.0) / (2.0 * math.pi)
RAY = complex(-SIGMA, 1.0)
OMEGA = np.linspace(1e-3, 2.0 * math.pi, 20001)  # ωL
RATIOS = [0.1, 0.2, 0.3, 0.5, 1.0, 1.4, 1.6, 2.0, 3.0, 5.0, 10.0, 30.0, 60.0, 100.0, 1000.0]


def p_gain(r: float, s):
    """K with 1 + s·r + K·e^{−s} = 0."""
    return -(1.0 + s * r) * np.exp(s)


def pi_time(r: float, s):
    """T_I with (1 + s·r)·T_I·s + K·(T_I·s + 1)·e^{−s} = 0, K = 0.9·r."""
    k = 0.9 * r
    return -k * np.exp(-s) / (s * (1.0 + s * r + k * np.exp(-s)))


def pd_time(r: float, s, lam: float = 1.2):
    """T_D with 1 + s·r + K·(1 + T_D·s)·e^{−s} = 0, K = λ·r."""
    k = lam * r
    return -(1.0 + s * r + k * np.exp(-s)) / (k * s * np.exp(-s))


def on_the_ray(value_at) -> list[tuple[float, float]]:
    """(ωL, setting) where value_at(ω(−σ + i)) is real and positive, lowest ω first."""
    im = value_at(OMEGA * RAY).imag
    out = []
    for i in np.nonzero(np.sign(im[:-1]) != np.sign(im[1:]))[0]:
        w = brentq(lambda w: value_at(w * RAY).imag, OMEGA[i], OMEGA[i + 1], xtol=1e-15)
        z = value_at(w * RAY)
        if abs(z) < 1e6 and z.real > 0:  # a pole's sign change runs off to infinity
            out.append((w, z.real))
    return out


def independent(r: float) -> dict[str, float | list[float]]:
    ku, pu = ultimate_point([1.0], [r, 1.0], 1.0)
    w4, k4 = on_the_ray(lambda s: p_gain(r, s))[0]
    _, ti = on_the_ray(lambda s: pi_time(r, s))[0]
    tds = [td for _, td in on_the_ray(lambda s: pd_time(r, s))]
    return {
        "k0rl": ku / r,
        "tau0": pu,
        "w4l": w4,
        "k0_over_k4": ku / k4,
        "k4rl": k4 / r,
        "ti4": ti,
        "td4": tds,
    }


@pytest.mark.parametrize("r", RATIOS)
def test_the_closed_forms_solve_the_characteristic_equation(r):
    want = independent(r)
    cf = ih.closed_form(r)
    assert cf.k0rl == pytest.approx(want["k0rl"], rel=1e-7)
    assert cf.tau0 == pytest.approx(want["tau0"], rel=1e-7)
    assert cf.w4l == pytest.approx(want["w4l"], rel=1e-7)
    assert cf.k0_over_k4 == pytest.approx(want["k0_over_k4"], rel=1e-7)
    assert cf.k4rl == pytest.approx(want["k4rl"], rel=1e-7)
    assert cf.ti4 == pytest.approx(want["ti4"], rel=1e-7)
    assert [td for _, td in cf.pd] == pytest.approx(want["td4"], rel=1e-7)


def test_the_pd_branches_and_where_they_part():
    """Below T/L ≈ 1.49 one T_D (curve b); above it a second, lower one (b′) that starts from
    T_D = 0 where P alone at 1.2/(R·L) already gives 25 % (K₄·R·L = 1.2)."""
    k4rl = lambda r: on_the_ray(lambda s: p_gain(r, s))[0][1] / r  # noqa: E731
    parting = brentq(lambda r: k4rl(r) - 1.2, 1.0, 3.0, xtol=1e-12)
    assert ih.pd_two_branches_above() == pytest.approx(parting, rel=1e-7)
    assert 1.43 < parting < 1.5  # the paper reads 1.43
    assert len(ih.quarter_pd(parting * 0.99)) == 1 and len(ih.quarter_pd(parting * 1.01)) == 2
    lower, upper = ih.quarter_pd(1.02 * parting)
    assert lower[0] < upper[0] and lower[1] < 0.03 < upper[1]  # b′: lower ω, T_D from 0
    # curve b is flat for T/L ≥ 1.5, 0.353–0.362: the paper's rule says 0.36–0.37
    for r in (1.5, 3.0, 10.0, 100.0, 1e4):
        assert 0.353 < ih.closed_form(r).td4_upper < 0.362


def test_zn_integral_time_is_longer_than_needed_below_t_over_l_60():
    ti = lambda r: on_the_ray(lambda s: pi_time(r, s))[0][1]  # noqa: E731
    meet = brentq(lambda r: ti(r) - 10.0 / 3.0, 10.0, 1000.0, xtol=1e-10)
    assert ih.ti4_meets_zn() == pytest.approx(meet, rel=1e-6)
    assert meet == pytest.approx(60.0, abs=1.0)  # the paper: "T/L < 60"
    assert ih.closed_form(30.0).ti4 < ih.ZN_TI < ih.closed_form(100.0).ti4


def test_the_limits():
    """T/L → 0 (a pure delay): e^{−Ls} alone with P gain K has roots ln K + i(2k+1)π, so
    25 % needs K₄ = e^{−σπ} = ½ = K₀/2: ZN's P rule is exact there. T/L → ∞ (an integrator
    with dead time): the 25 % pair of (T·s + K·e^{−s}) has tan ω = 1/σ (eq. 7's limit),
    K₄·R·L = ω·e^{−σω}/sin ω."""
    assert ih.closed_form(1e-5).k0_over_k4 == pytest.approx(2.0, rel=1e-4)
    w = math.atan(1.0 / SIGMA)
    f = ih.findings()
    assert f["k4rl_limit"] == pytest.approx(w * math.exp(-SIGMA * w) / math.sin(w), rel=1e-5)
    w0 = math.pi / 2  # K₀·R·L → π/2
    assert f["k0_over_k4_limit"] == pytest.approx(w0 / f["k4rl_limit"], rel=1e-5)


def test_the_ideal_pd_high_frequency_roots_tend_to_ln_lambda_td():
    """A root of 1 + s·r + K(1 + T_D·s)·e^{−s} far up the imaginary axis, by Newton from
    ln(λ·T_D) + i(2k+1)π, has that real part; below T/L ≈ 0.42 they decay slower than curve
    b's pair, which the module reports."""
    r = 1.0
    td, lam = ih.quarter_pd(r)[-1][1], 1.2
    k = lam * r
    s = complex(math.log(lam * td), 41 * math.pi)
    for _ in range(50):
        f = 1 + s * r + k * (1 + td * s) * np.exp(-s)
        df = r + k * td * np.exp(-s) - k * (1 + td * s) * np.exp(-s)
        s -= f / df
    assert abs(1 + s * r + k * (1 + td * s) * np.exp(-s)) < 1e-9
    assert -s.real == pytest.approx(ih.chain_decay(td), abs=0.02)
    below = ih.pd_chain_dominates_below()
    assert 0.3 < below < 0.5
    assert not ih.closed_form(0.3).pd_dominated(-1) and ih.closed_form(0.6).pd_dominated(-1)


def check_closed_forms(rows: dict[str, list[dict]]) -> None:
    """Every closed-form value of the three tables within 0.5 % of the independent one."""
    for f1, f2, f3 in zip(rows["fig1"], rows["fig2"], rows["fig3"], strict=True):
        r = f1["t_over_l"]
        want = independent(r)
        assert f1["k0_over_k4"] == pytest.approx(want["k0_over_k4"], rel=5e-3), r
        assert f1["k4rl"] == pytest.approx(want["k4rl"], rel=5e-3), r
        assert f2["k0rl"] == pytest.approx(want["k0rl"], rel=5e-3), r
        assert f2["tau0"] == pytest.approx(want["tau0"], rel=5e-3), r
        assert f3["ti4"] == pytest.approx(want["ti4"], rel=5e-3), r
        tds = [f3["td4_lower"], f3["td4_upper"]] if f3["td4_lower"] else [f3["td4_upper"]]
        assert tds == pytest.approx(want["td4"], rel=5e-3), r


def test_benchmark_iinoya_hotta_json(capsys):
    """The acceptance: closed forms within 0.5 % of the independent solution at every T/L;
    at T/L = 1 the measured points within 2 % of the curves, or a note saying why not."""
    argv = ["benchmark", "--iinoya-hotta", "--json", "--ratios", "0.1,10,100", "--measure", "1"]
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["t_over_l"] for r in doc["fig1"]] == [0.1, 1.0, 10.0, 100.0]
    check_closed_forms(doc)
    f1, f2, f3 = (doc[k][1] for k in ("fig1", "fig2", "fig3"))
    for row, key in ((f1, "k0_over_k4"), (f1, "k4rl"), (f2, "k0rl"), (f2, "tau0"), (f3, "ti4")):
        assert abs(row[f"{key}_error"]) < 0.02, key
    # the response at the curves' P and PI settings decays as the pair does
    assert f1["decay_ratio_at_closed_form"] == pytest.approx(0.25, abs=ih.DR_SLACK)
    assert f3["decay_ratio_pi_at_closed_form"] == pytest.approx(0.25, abs=ih.DR_SLACK)
    # ZN's P rules damp more than 25 % at T/L = 1 (K₀/K₄ < 2, K₄·R·L > 1)
    assert f1["decay_ratio_zn_ultimate"] < 0.25 and f1["decay_ratio_zn_reaction"] < 0.25
    # PD at T/L = 1: the response at eq. 15's T_D is not the pair's: measured off, and said
    assert f3["td4_upper_measured"] is not None
    off = abs(f3["td4_upper_error"]) > 0.02
    not_pair = abs(f3["decay_ratio_pd_upper_at_closed_form"] - 0.25) > ih.DR_SLACK
    assert not off or not_pair
    assert not_pair == any("does not dominate" in n and "(b)" in n for n in f3["notes"])
    assert off == any("off the curve" in n and "(b)" in n for n in f3["notes"])
    # a row off by more than 2 % always carries a note
    for rows, keys in (("fig1", ("k0_over_k4", "k4rl")), ("fig3", ("ti4", "td4_upper"))):
        for row in doc[rows]:
            for key in keys:
                err = row.get(f"{key}_error")
                if err is not None and abs(err) > 0.02:
                    assert row["notes"], (rows, row["t_over_l"], key)
    f = doc["findings"]
    assert f["ti4_equals_zn_at_t_over_l"] == pytest.approx(60.45, abs=0.01)
    assert doc["experiments"][0]["dead_time"] == pytest.approx(1.0, rel=1e-6)  # the step test


def test_closed_forms_only_and_the_plots(tmp_path, capsys):
    out = tmp_path / "figs"
    argv = ["benchmark", "--iinoya-hotta", "--ratios", "0.1,1,10,100", "--measure", ""]
    assert main([*argv, "--plot", str(out)]) == 0
    text = capsys.readouterr().out
    assert "Fig. 1" in text and "Fig. 2" in text and "Fig. 3" in text
    assert "Ku ours" not in text  # the relay suite does not run
    for n in (1, 2, 3):
        png = out / f"iinoya_hotta_fig{n}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["--plot", "x"], "--plot"),
        (["--measure", "1"], "--measure"),
        (["--iinoya-hotta", "--measure", "1000"], "--measure"),
        (["--iinoya-hotta", "--measure", "a"], "--measure"),
        (["--iinoya-hotta", "--ratios", "0"], "--ratios"),
        (["--iinoya-hotta", "--ratios", "", "--measure", ""], "--ratios"),
    ],
)
def test_bad_flags_are_refused_in_one_line(argv, flag):
    with pytest.raises(SystemExit, match=flag) as stop:
        main(["benchmark", *argv])
    assert stop.value.code == 2


def test_a_plot_path_that_is_a_file_is_refused(tmp_path, capsys):
    f = tmp_path / "f"
    f.write_text("")
    assert main(["benchmark", "--iinoya-hotta", "--measure", "", "--plot", str(f)]) == 2
    err = capsys.readouterr().err.strip()
    assert "--plot" in err and "not a directory" in err and "\n" not in err
