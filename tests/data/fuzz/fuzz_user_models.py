"""User model classes that misbehave, for the plant-file fuzz tests (``model =
"fuzz_user_models:Class"``, importable once this folder is on the path)."""

from __future__ import annotations

import math
import sys
import time


class Good:
    """A first-order lag; the base of the misbehaving ones."""

    pv_units = "bar"
    pv_range = (0.0, 100.0)

    def __init__(self, sample_time: float, op0: float = 50.0, fail_after: int = 10**9):
        self.sample_time, self.op0, self.fail_after = sample_time, op0, fail_after
        self.pv = op0
        self.steps = 0
        self.bias = 0.0

    def reset(self) -> float:
        self.pv = self.op0
        return self.pv

    def step(self, op: float) -> float:
        self.steps += 1
        self.pv += 0.1 * (op + self.bias - self.pv)
        return self.pv

    def disturbance_names(self) -> tuple[str, ...]:
        return ("bias",)

    def set_disturbance(self, name: str, value: float) -> None:
        self.bias = value


class RaisesInInit(Good):
    def __init__(self, sample_time: float, **kw):
        raise RuntimeError("the valve map file vmap.csv is missing")


class MultilineError(Good):
    def __init__(self, sample_time: float, **kw):
        raise ValueError("first line\nsecond line\n\tthird line")


class ExitsInInit(Good):
    def __init__(self, sample_time: float, **kw):
        sys.exit(3)


class ResetRaises(Good):
    def reset(self) -> float:
        raise ZeroDivisionError("no rest state at op0")


class ResetExits(Good):
    def reset(self) -> float:
        sys.exit(3)


class ResetSleeps(Good):
    """A reset() that blocks (waits on a device that never answers)."""

    def reset(self) -> float:
        time.sleep(600.0)
        return self.pv


class ResetRetries(Good):
    """A reset() that retries whatever goes wrong (``except Exception``), for good."""

    def reset(self) -> float:
        while True:
            try:
                time.sleep(600.0)
            except Exception:
                continue


class ResetNaN(Good):
    def reset(self) -> float:
        return math.nan


class ResetString(Good):
    def reset(self) -> str:
        return "fifty"


class ResetNone(Good):
    def reset(self) -> None:
        return None


class StepRaisesAfter(Good):
    def step(self, op: float) -> float:
        if self.steps >= self.fail_after:
            raise RuntimeError(f"sensor fault after {self.steps} steps")
        return super().step(op)


class StepExitsAfter(Good):
    """A user's sys.exit() in step(): the loop faults, the plant runs on."""

    def step(self, op: float) -> float:
        if self.steps >= self.fail_after:
            sys.exit(4)
        return super().step(op)


class StepNaNAfter(Good):
    def step(self, op: float) -> float:
        pv = super().step(op)
        return math.nan if self.steps > self.fail_after else pv


class StepInfAfter(Good):
    def step(self, op: float) -> float:
        pv = super().step(op)
        return math.inf if self.steps > self.fail_after else pv


class StepOverflows(Good):
    """Its state grows tenfold a step: a float overflow (OverflowError from **)."""

    def step(self, op: float) -> float:
        self.steps += 1
        return 10.0 ** (self.steps * 40)


class StepReturnsList(Good):
    def step(self, op: float) -> list:
        return [op]


class PropertyRaises(Good):
    @property
    def pv_units(self) -> str:
        raise KeyError("units")


class NoStep:
    pv_units = "bar"
    pv_range = (0.0, 1.0)
    op0 = 50.0

    def __init__(self, sample_time: float):
        self.sample_time = sample_time

    def reset(self) -> float:
        return 0.5

    def disturbance_names(self) -> tuple[str, ...]:
        return ()

    def set_disturbance(self, name: str, value: float) -> None:
        raise KeyError(name)


class StepNotCallable(Good):
    step = 5.0


class NamesNotNames(Good):
    """disturbance_names() returns a number: it was taken, its status showing no disturbance."""

    def disturbance_names(self):
        return 5


class Knobs(Good):
    """Its protocol attributes come from the plant file, whatever they are (``set_NAME``:
    NAME is a key the plant file keeps for itself)."""

    def __init__(self, sample_time: float, **attrs):
        super().__init__(sample_time)
        for k, v in attrs.items():
            setattr(self, k.removeprefix("set_"), v)


class DisturbanceRaises(Good):
    def set_disturbance(self, name: str, value: float) -> None:
        raise ZeroDivisionError("bias divides by zero")


class NamesRaise(Good):
    def disturbance_names(self) -> tuple[str, ...]:
        raise RuntimeError("no names today")


class _Later(Good):
    """Names as it should at load (its first answer), then ``later()``'s."""

    calls = 0

    def disturbance_names(self):
        self.calls += 1
        return ("bias",) if self.calls == 1 else self.later()


class NamesRaiseLater(_Later):
    def later(self) -> tuple[str, ...]:
        raise RuntimeError("no names today")


class NamesJunkLater(_Later):
    def later(self) -> tuple:
        return (1, None, "bias", "ghost")


class StepHugeInt(Good):
    """An int past a float's range: ``float()`` of it overflows (`model check` exit 70)."""

    def step(self, op: float) -> float:
        self.steps += 1
        return 10**400 if self.steps >= self.fail_after else super().step(op)


class OwnNumDen(Good):
    """Attributes of its own named ``num`` and ``den`` (a tube count, a density): no transfer
    function (`model check`: "'int' object is not iterable", exit 70)."""

    def __init__(self, sample_time: float, op0: float = 50.0, fail_after: int = 10**9):
        super().__init__(sample_time, op0, fail_after)
        self.num, self.den = 4, 998.2


class Chatty(Good):
    """Prints in its __init__ and step(): `model check --json` began with its lines."""

    def __init__(self, sample_time: float, op0: float = 50.0, fail_after: int = 10**9):
        super().__init__(sample_time, op0, fail_after)
        print("hello from __init__")

    def step(self, op: float) -> float:
        print("hello from step", op)
        return super().step(op)
