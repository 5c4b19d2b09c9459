"""On the realtime clock the plant restores a leased loop at the first sample whose PV is
outside the limits its lease names: the loop runs on between its supervisor's commands, and a
supervisor paused mid-test (SIGSTOP) held a relay's output while the PV ran on past its limits
until the lease timed out. The plant service runs in this process, its clock ticked by the
test (``PlantService.tick``, one period of the loops of a sample time, as its clock thread
does on the wall clock)."""

from __future__ import annotations

import pydantic
import pytest

from services.plant_sim.plant_file import build_plant
from services.plant_sim.service import PlantService, ServiceOptions
from shared import keys, wire
from shared.control.beyond import beyond
from shared.messages import (
    LeaseCommand,
    LoopStatus,
    ModeCommand,
    OutputCommand,
    ProcessSample,
    ReleaseCommand,
    SyncCommand,
)
from shared.session import open_session
from tests.test_plant_stream import ALONE, SPEC

PREFIX = "limits"


class Caught:
    """Stands in for the plant's publishers: keeps what it is given, in order."""

    def __init__(self):
        self.sent: list[tuple[str, bytes]] = []

    def put_json(self, key, model, payload) -> None:
        self.sent.append((key, payload))

    def put(self, key, msg) -> None:
        self.put_json(key, type(msg), wire.encode(msg))

    def held_since(self):
        return None

    def decoded(self) -> list[ProcessSample | LoopStatus]:
        out = []
        for key, payload in self.sent:
            if key == keys.pv(PREFIX, "x"):
                out.append(wire.decode(ProcessSample, payload))
            elif key == keys.status(PREFIX, "x"):
                out.append(wire.decode(LoopStatus, payload))
        return out


@pytest.fixture()
def service():
    with open_session(ALONE) as session:
        plant = build_plant({"seed": 4, "loops": {"x": SPEC}})
        yield PlantService(session, plant, ServiceOptions(prefix=PREFIX, clock="realtime"))


def send(svc: PlantService, cmd) -> None:
    svc.handle_command(keys.command(PREFIX, "x", cmd.kind), wire.encode(cmd), None)


def push(svc: PlantService, limits: tuple[float, float] | None, by: float = 20.0) -> Caught:
    """Lease the loop (with ``limits``), put it in manual ``by`` % above its output (the PV
    rises by 1.5 × that at rest: far past any limit named here), and tick the clock until the
    lease ends or 200 periods (20 s) have passed."""
    send(svc, LeaseCommand(loop="x", source="me", timeout=600.0, t=0.0, pv_limits=limits))
    caught = svc.publishers = Caught()
    op = svc.loops["x"].op
    send(svc, ModeCommand(loop="x", mode="manual", source="me"))
    send(svc, OutputCommand(loop="x", op=op + by, source="me"))
    group = svc.steppers.groups[0]
    for _ in range(200):
        svc.tick(group)
        if "x" not in svc.leases:
            break
    return caught


def test_the_first_pv_past_the_limits_restores_the_loop(service) -> None:
    before = service.loops["x"].snapshot()
    pv0 = service.loops["x"].pv
    hi = pv0 + 1.0
    caught = push(service, (pv0 - 1.0, hi))
    assert "x" not in service.leases
    got = [m for m in caught.decoded() if isinstance(m, ProcessSample)]
    assert all(s.pv <= hi for s in got[:-1]) and got[-1].pv > hi  # ended at the first past
    watchdog = [m for m in caught.decoded() if isinstance(m, LoopStatus)][-1]
    assert watchdog.reason == "watchdog"
    assert watchdog.ended == (
        f"the PV {beyond(got[-1].pv, pv0 - 1.0, hi)} left the experiment's limits "
        f"[{pv0 - 1.0:g}, {hi:g}]"
    )
    assert watchdog.t == got[-1].t  # said at the sample that crossed them
    loop = service.loops["x"].snapshot()
    assert (loop.mode, loop.op, loop.sp, loop.gains) == (
        before.mode,
        before.op,
        before.sp,
        before.gains,
    )
    # its holder's writes are refused from then on, said with why the lease ended
    send(service, OutputCommand(loop="x", op=90.0, source="me"))
    assert service.loops["x"].op == before.op
    assert "left the experiment's limits" in service.lapsed["x"]["me"]


def test_limits_at_the_range_are_left_where_the_pv_clips_at_its_end(service) -> None:
    """The default limits are the PV's range, and the transmitter clips the PV at its ends:
    a PV held there would never be outside them (review: a paused tuner's push sat at the
    range's end until the lease timed out)."""
    lo, hi = service.loops["x"].settings.pv_range
    caught = push(service, (lo, hi), by=40.0)  # 52 + 1.5 × 40 is past the top
    assert "x" not in service.leases
    got = [m for m in caught.decoded() if isinstance(m, ProcessSample)]
    assert got[-1].pv == hi and all(s.pv < hi for s in got[:-1])
    ended = [m for m in caught.decoded() if isinstance(m, LoopStatus)][-1].ended
    assert ended.startswith(f"the PV {hi:g} reached an end of its range [{lo:g}, {hi:g}]")


def test_a_lease_without_limits_is_left_to_its_holder(service) -> None:
    caught = push(service, None)
    assert service.leases["x"].source == "me"  # 20 s on, 20 % up: still held
    got = [m for m in caught.decoded() if isinstance(m, ProcessSample)]
    assert len(got) == 200 and got[-1].pv > got[0].pv + 10.0


def test_a_holder_renewing_its_lease_names_its_limits_anew(service) -> None:
    pv0 = service.loops["x"].pv
    send(service, LeaseCommand(loop="x", source="me", timeout=600.0, t=0.0))
    send(service, SyncCommand(loop="x", token=1, source="me"))
    assert service.leases["x"].pv_limits is None
    caught = push(service, (pv0 - 1.0, pv0 + 1.0))
    assert "x" not in service.leases
    assert caught.decoded()[-1].reason == "watchdog"


def test_the_new_fields_are_checked_and_left_off_the_wire_when_none(service) -> None:
    with pytest.raises(pydantic.ValidationError, match="pv_limits: low 3 is not below high"):
        LeaseCommand(loop="x", source="me", pv_limits=(3.0, 3.0))
    # a service of an earlier version refuses a field it does not know, and the message
    assert b"pv_limits" not in wire.encode(LeaseCommand(loop="x", source="me"))
    assert b"ended" not in wire.encode(service.loop_status(service.loops["x"], "query"))


def test_a_pv_past_its_limits_reads_outside_them() -> None:
    assert beyond(59.7953, 59.8, 60.2) == "59.795"  # not "59.8", on the limit as printed
    assert beyond(61.02, 59.0, 61.0) == "61.02"
    assert beyond(60.2000001, 59.8, 60.2) == "60.2000001"
    # past limits that print shorter than they are: past them as printed too
    assert beyond(59.9999997, 40.0, 59.9999996) == "59.9999997"


def test_the_lease_ended_is_the_one_whose_pv_crossed(service) -> None:
    """The plant ended the lease after publishing the crossing sample, outside its lock: a
    release and another supervisor's lease in between had the newcomer's lease ended in its
    place (review). It is ended in the same hold of the lock as the look that found it."""
    pv0 = service.loops["x"].pv
    caught = Caught()

    def meanwhile(key, model, payload) -> None:
        caught.sent.append((key, payload))
        if key == keys.pv(PREFIX, "x") and wire.decode(ProcessSample, payload).pv > pv0 + 1.0:
            send(service, ReleaseCommand(loop="x", source="me"))
            send(service, LeaseCommand(loop="x", source="other", timeout=600.0, t=0.0))

    caught.put_json = meanwhile
    send(service, LeaseCommand(loop="x", source="me", timeout=600.0, t=0.0, pv_limits=(0, pv0 + 1)))
    service.publishers = caught
    op = service.loops["x"].op
    send(service, ModeCommand(loop="x", mode="manual", source="me"))
    send(service, OutputCommand(loop="x", op=op + 20.0, source="me"))
    for _ in range(200):
        service.tick(service.steppers.groups[0])
        if service.leases.get("x") is not None and service.leases["x"].source == "other":
            break
    assert service.leases["x"].source == "other"
    assert "other" not in service.lapsed.get("x", {})


def test_a_replayed_command_never_reaches_the_loop(service) -> None:
    """`autotune replay --with-commands` on the live prefix: its lease (under the recorded
    run's id), mode, output and gains were applied to the live loop: flow1 stepped to 55 %
    and left with the recorded run's gains, filed in the change history as that run's
    (helper trial). A command marked as a replay is refused, whatever it is."""
    from types import SimpleNamespace

    mark = SimpleNamespace(to_bytes=lambda: wire.replay_attachment("run.mcap"))
    before = service.loops["x"].snapshot()
    for cmd in (
        LeaseCommand(loop="x", source="tuner:r1", timeout=600.0, t=0.0),
        ModeCommand(loop="x", mode="manual", source="tuner:r1"),
        OutputCommand(loop="x", op=before.op + 15.0, source="tuner:r1"),
    ):
        sample = SimpleNamespace(
            key_expr=keys.command(PREFIX, "x", cmd.kind),
            payload=SimpleNamespace(to_bytes=lambda cmd=cmd: wire.encode(cmd)),
            encoding=wire.JSON,
            attachment=mark,
        )
        service._on_command(sample)
    assert "x" not in service.leases
    after = service.loops["x"].snapshot()
    assert (after.mode, after.op) == (before.mode, before.op)
    assert service.rejected_by_reason["replay"] == 3
    # and against the loop, as `autotune loops x --json` shows them (it said 0 refusals)
    assert service.loops["x"].rejected == 3
    assert "replayed from run.mcap" in service.loops["x"].last_reject
