"""A plant started anew while a run had lost it is said to be one: the loop is as its plant
file sets it. Killed and restarted mid-tune, it was blamed on "this run's last writes, read by
the plant after the run lost it, or another client" (helper trial). Its info's ``instance``
(drawn at each plant start) tells it from the plant the run began on."""

from __future__ import annotations

from services.autotuner.tuning import TuningRun
from services.offline.local_loop import LocalLoopClient
from services.plant_sim.plant_file import build_plant
from shared.messages import TuneRequest

SPEC = {"model": "fopdt", "gain": 1.0, "time_constant": 3.0, "delay": 0.5, "sample_time": 0.1}


class Restarted(LocalLoopClient):
    """The loop's info as a plant started anew answers it: another instance."""

    def query_info(self, timeout: float):
        return self.info.model_copy(update={"instance": "another"})


def _seen(client: LocalLoopClient) -> dict:
    client.info = client.info.model_copy(update={"instance": "first"})
    run = TuningRun(client, TuneRequest(loop="x", method="relay"), "t")
    before = client.sync()
    run._pv_rest = before.pv  # where the run found the PV at rest
    return run._seen_after_loss(before)


def test_a_plant_started_anew_is_told_from_the_one_the_run_began_on():
    assert _seen(Restarted(build_plant({"loops": {"x": SPEC}}, "t")["x"]))["restarted"] is True
    same = LocalLoopClient(build_plant({"loops": {"x": SPEC}}, "t")["x"])
    assert _seen(same)["restarted"] is False
