"""Plant files: presets, the minimum form, user model classes, errors naming loop and field."""

import sys
import textwrap

import numpy as np
import pytest

from services.plant_sim.plant_file import build_plant, default_plant_path, load_plant_file
from services.plant_sim.simulation.loop import CommandRejected
from shared.errors import ConfigError
from shared.messages import DisturbanceCommand, ModeCommand, OutputCommand, SetpointCommand

MINIMUM = """
[loops.hx1]
model = "transfer_function"   # or a preset name, or "package.module:Class"
num = [1.0]
den = [600.0, 70.0, 1.0]
delay = 5.0
sample_time = 0.25
noise_std = 0.0               # PV units
"""


def test_minimum_form_from_the_issue(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text(MINIMUM)
    loops = load_plant_file(path)
    hx1 = loops["hx1"]
    assert hx1.sample_time == 0.25 and hx1.settings.noise_std == 0.0
    assert hx1.process.discrete.delay_samples == 20


def test_default_plant_serves_every_preset_at_rest():
    loops = load_plant_file(default_plant_path())
    assert set(loops) == {"hx1", "hx2", "lvl1", "lvl2", "flow1"}
    for loop in loops.values():
        pvs = np.array([loop.advance().pv for _ in range(200)])
        noise = loop.settings.noise_std
        # at rest: the PV stays within its noise band of the setpoint (the rest value)
        assert np.max(np.abs(pvs - loop.sp)) <= 6 * noise + 1e-9, loop.settings.loop_id


def test_noise_is_deterministic_given_the_seed():
    a = load_plant_file(default_plant_path(), seed=5)["hx1"]
    b = load_plant_file(default_plant_path(), seed=5)["hx1"]
    c = load_plant_file(default_plant_path(), seed=6)["hx1"]
    pa = [a.advance().pv for _ in range(50)]
    assert pa == [b.advance().pv for _ in range(50)]
    assert pa != [c.advance().pv for _ in range(50)]


@pytest.mark.parametrize(
    ("toml", "needle"),
    [
        ('[loops.hx1]\nmodel = "nope"', "loops.hx1.model: unknown model 'nope'"),
        (
            '[loops.hx1]\nmodel = "transfer_function"\nnum=[1]\nden=[1,1]',
            "loops.hx1.sample_time: required",
        ),
        (
            '[loops.hx1]\nmodel = "transfer_function"\nden=[1,1]\nsample_time=1',
            "loops.hx1.num: required",
        ),
        ('[loops.hx1]\nmodel = "heat_exchanger"\ntau3 = 4', "loops.hx1.tau3: not a parameter"),
        (
            '[loops.hx1]\nmodel = "heat_exchanger"\nsample_time = -1',
            "loops.hx1.sample_time: Input should be greater than 0",
        ),
        (
            '[loops.hx1]\nmodel = "heat_exchanger"\ndelay = "5"',
            "loops.hx1.delay: expected a number",
        ),
        (
            '[loops.hx1]\nmodel = "fopdt"\ngain=1\ntime_constant=0\nsample_time=1',
            "loops.hx1.time_constant: must be > 0",
        ),
        ('[loops.hx1]\nmodel = "heat_exchanger"\nop_limits = [50, 20]', "loops.hx1.op_limits"),
        ('[loops.hx1]\nmodel = "heat_exchanger"\nsetpoint = 500.0', "loops.hx1.setpoint"),
        ('[loops.hx1]\nmodel = "heat_exchanger"\n[loops.hx1.pid]\nkc = -1.0', "loops.hx1.pid.kc"),
        ('[loops."bad id"]\nmodel = "heat_exchanger"', "loops.bad id"),
        ('[loops.t1]\nmodel = "flow"\ncharacteristic = "butterfly"', "loops.t1.characteristic"),
        ('[loops.t1]\nmodel = "no_such_pkg.mod:Plant"', "loops.t1.model: cannot import"),
        ("[loops]", "loops: Dictionary should have at least 1 item"),
    ],
)
def test_bad_plant_files_name_the_loop_and_field(tmp_path, toml, needle):
    path = tmp_path / "bad.toml"
    path.write_text(toml)
    with pytest.raises(ConfigError) as err:
        load_plant_file(path)
    assert needle in str(err.value)
    assert str(path) in str(err.value)


def test_not_toml_and_missing_file(tmp_path):
    bad = tmp_path / "x.toml"
    bad.write_text("[loops.hx1\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_plant_file(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_plant_file(tmp_path / "missing.toml")


def test_user_model_class_is_swapped_in(tmp_path, monkeypatch):
    (tmp_path / "my_plants.py").write_text(
        textwrap.dedent('''
        class Doubler:
            """PV = 2·op, one sample late."""
            pv_units = "bar"
            pv_range = (0.0, 300.0)

            def __init__(self, sample_time, op0=10.0, offset=0.0):
                self.sample_time, self.op0, self.offset = sample_time, op0, offset
                self.bias = 0.0

            def reset(self):
                return 2 * self.op0 + self.offset

            def step(self, op):
                return 2 * op + self.offset + self.bias

            def disturbance_names(self):
                return ("bias",)

            def set_disturbance(self, name, value):
                self.bias = value

        class Rangeless:
            """No pv_range, pv_units of its own: the plant file gives them."""

            def __init__(self, sample_time, op0=10.0):
                self.sample_time, self.op0 = sample_time, op0

            def reset(self):
                return self.op0

            def step(self, op):
                return op

            def disturbance_names(self):
                return ()

            def set_disturbance(self, name, value):
                raise KeyError(name)

        class Broken:
            def __init__(self, sample_time):
                pass
    ''')
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    loops = build_plant(
        {"loops": {"p1": {"model": "my_plants:Doubler", "sample_time": 0.5, "offset": 1.0}}}
    )
    p1 = loops["p1"]
    assert p1.pv == 21.0 and p1.settings.pv_units == "bar"
    p1.apply(OutputCommand(loop="p1", op=30.0))
    assert p1.advance().pv == 61.0
    p1.apply(DisturbanceCommand(loop="p1", name="bias", value=-1.0))
    assert p1.advance().pv == 60.0
    given = {"model": "my_plants:Rangeless", "pv_range": [0.0, 50.0], "pv_units": "kPa"}
    p3 = build_plant({"loops": {"p3": {**given, "sample_time": 1.0}}})["p3"]
    assert p3.settings.pv_range == (0.0, 50.0) and p3.settings.pv_units == "kPa"
    with pytest.raises(ConfigError, match=r"loops\.p4\.model: .*\(missing: pv_units, pv_range\)"):
        build_plant({"loops": {"p4": {"model": "my_plants:Rangeless", "sample_time": 1.0}}})
    with pytest.raises(ConfigError, match=r"loops\.p2\.model: my_plants:Broken does not implement"):
        build_plant({"loops": {"p2": {"model": "my_plants:Broken", "sample_time": 1.0}}})
    sys.modules.pop("my_plants", None)


def test_loop_refuses_out_of_range_commands_and_changes_nothing():
    loop = build_plant({"loops": {"hx1": {"model": "heat_exchanger", "op_limits": [10, 90]}}})[
        "hx1"
    ]
    before = (loop.op, loop.sp, loop.mode)
    for cmd in (
        OutputCommand(loop="hx1", op=95.0),
        SetpointCommand(loop="hx1", sp=400.0),
        DisturbanceCommand(loop="hx1", name="steam", value=1.0),
        DisturbanceCommand(loop="hx1", name="load", value=500.0),
    ):
        with pytest.raises(CommandRejected):
            loop.apply(cmd)
    loop.apply(ModeCommand(loop="hx1", mode="auto"))
    with pytest.raises(CommandRejected, match="in auto"):
        loop.apply(OutputCommand(loop="hx1", op=50.0))
    assert (loop.op, loop.sp) == before[:2]


def test_a_transfer_function_of_absurd_order_is_refused_at_once(tmp_path):
    """den = s^3000 + 1 took 28 s to be refused (as unstable), s^100000 + 1 tried to allocate
    75 GiB: the order is bounded before any matrix is built."""

    path = tmp_path / "big.toml"
    den = ", ".join(["1.0"] + ["0.0"] * 2999 + ["1.0"])
    path.write_text(
        f'[loops.a]\nmodel = "transfer_function"\nnum = [1.0]\nden = [{den}]\nsample_time = 0.1\n'
    )
    with pytest.raises(ConfigError) as err:
        load_plant_file(path)
    assert "loops.a.den: 3001 coefficients (order 3000); at most 101 (order 100)" in str(err.value)
    path.write_text(
        f'[loops.a]\nmodel = "transfer_function"\nnum = [{den}]\nden = [1.0, 1.0]\n'
        "sample_time = 0.1\n"
    )
    with pytest.raises(ConfigError, match=r"loops\.a\.num: 3001 coefficients"):
        load_plant_file(path)


def test_a_transfer_function_of_order_forty_still_loads(tmp_path):
    from math import comb

    path = tmp_path / "lags.toml"
    den = ", ".join(str(float(comb(40, k))) for k in range(41))  # (s + 1)^40
    path.write_text(
        f'[loops.a]\nmodel = "transfer_function"\nnum = [1.0]\nden = [{den}]\nsample_time = 0.1\n'
    )
    assert load_plant_file(path)["a"].process.discrete is not None
