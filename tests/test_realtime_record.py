"""On the realtime clock the samples that came while the run computed, or waited for a
command's confirmation, are held for it and read next, in order. A verification's record
starts with the plant's application of its gains: the samples held from before ran under what
the loop held before. A starved tuner (flow1's ramp at ×50, three tunes at once on a loaded
machine) read 93 s of the ramp's P-only calming, held while its design computed, as its new
gains' response, and rejected them as "did not settle (it rests +1.16 off it)": the gains had
not yet run a sample (helper trial). Here a realtime loop in this process holds what its plant
steps while the run computes, as ``LoopClient`` does."""

from __future__ import annotations

from collections import deque

from services.autotuner.tuning import RunHooks, TuningRun
from shared.messages import GainsCommand, TuneProgress, TuneRequest
from tests.test_tuning_run import RunningOnClient, third_order_loop

STARVED = 2000  # samples (40 s at 0.02 s) the plant steps while the run computes, each time


class HeldOnClient(RunningOnClient):
    """The realtime loop as ``LoopClient`` gives it: what the plant stepped while the run
    computed is held and read first (``hold_arrived``: ``STARVED`` samples, once ``starve`` is
    set); each sample's time is the plant's."""

    def __init__(self, loop):
        self.held: deque = deque()
        self.starve = False
        super().__init__(loop)

    def hold_arrived(self):
        if not self.starve:
            return []
        self.starve = False
        new = super().advance(STARVED)
        self.held.extend(new)
        return new

    def samples(self, steps, band=None, record=None):
        out = []
        while self.held and len(out) < steps:
            s = self.held.popleft()
            out.append(s)
            if band is not None and band.ends(s.pv, s.op):
                return out
        if len(out) < steps:
            out += super().advance(steps - len(out), band)
        return out


def test_a_verification_reads_no_sample_from_before_its_gains(monkeypatch):
    import services.autotuner.tuning as tuning

    monkeypatch.setattr(tuning, "COMPUTE_CHECK", 1e-3)  # every compute looks at what came
    client = HeldOnClient(third_order_loop("manual"))
    select, record = tuning.select, tuning.TuningRun._record
    records: list[tuple[float, float]] = []  # (the last command's time, the record's first)

    def starved_design(*args):  # the plant runs on under the ramp's last gain meanwhile
        client.starve = True
        return select(*args)

    def watched_record(self, *args, **kwargs):
        applied = client.applied_t
        out = record(self, *args, **kwargs)
        if len(out[0]):
            records.append((applied, float(out[0][0])))
        return out

    monkeypatch.setattr(tuning, "select", starved_design)
    monkeypatch.setattr(tuning.TuningRun, "_record", watched_record)
    marks: list[TuneProgress] = []
    req = TuneRequest(loop="x", method="ramp")
    r = TuningRun(client, req, "unit", RunHooks(progress=marks.append)).run()
    assert client.info.clock == "realtime"
    assert r.status == "ok", r.reason
    assert records and client.held == deque()  # every held sample was read
    # each record from the first sample under the command before it (40 s of samples held
    # from before the gains: read as theirs without the fix)
    assert all(first > applied for applied, first in records), records
    verify = next(p for p in marks if p.phase == "verify")
    gains = [c for c in client.commands if isinstance(c, GainsCommand) and (c.t or 0.0) >= verify.t]
    assert gains and gains[0].t == verify.t
    times = [p.t for p in marks]
    assert times == sorted(times), times
