"""Which loops of a plant file a process serves: ``--loops`` and ``--shard K/N``."""

from __future__ import annotations

import pytest

from services.plant_sim.shards import select_loops
from shared.errors import ConfigError

IDS = [f"l{i}" for i in range(7)]


def test_the_shards_partition_the_file_round_robin_in_file_order():
    shards = [select_loops(IDS, None, f"{k}/3") for k in (1, 2, 3)]
    assert shards == [["l0", "l3", "l6"], ["l1", "l4"], ["l2", "l5"]]
    assert sorted(i for s in shards for i in s) == sorted(IDS)  # every loop once
    assert select_loops(IDS, None, "1/1") == IDS == select_loops(IDS, None, None)


def test_loops_keeps_the_file_order_of_the_ids_named():
    assert select_loops(IDS, "l5, l1", None) == ["l1", "l5"]


@pytest.mark.parametrize(
    "loops, shard, says",
    [
        ("l1,zz,yy", None, "--loops: zz, yy not in the plant file"),
        ("l1,,l2", None, "--loops 'l1,,l2': expected loop ids separated by commas"),
        ("l1,l1", None, "l1 named more than once"),
        (None, "0/2", "--shard '0/2': expected K/N with 1 ≤ K ≤ N"),
        (None, "3/2", "--shard '3/2'"),
        (None, "1/x", "--shard '1/x'"),
        (None, "8/8", "--shard 8/8: the plant file has 7 loop(s), none for shard 8"),
        ("l1", "1/2", "--loops and --shard: give one of them, not both"),
    ],
)
def test_bad_selections_are_refused_naming_the_flag(loops, shard, says):
    with pytest.raises(ConfigError) as err:
        select_loops(IDS, loops, shard)
    assert says in str(err.value) and "\n" not in str(err.value)
