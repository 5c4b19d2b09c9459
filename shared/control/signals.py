"""Signal helpers on sampled records (numpy arrays of PV or output against time in s).

The sample type the experiments are fed: anything with ``t`` (s, sim time), ``pv`` (PV
units) and ``op`` (% of output), as the bus's ``ProcessSample`` and a replayed record are.
"""

from __future__ import annotations

from typing import Protocol


class Sample(Protocol):
    """One sample of a loop: sim time t (s), PV (engineering units), output op (%)."""

    @property
    def t(self) -> float: ...

    @property
    def pv(self) -> float: ...

    @property
    def op(self) -> float: ...
