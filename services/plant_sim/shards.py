"""Serving one plant file's loops from several plant processes, and refusing overlaps.

``--loops hx1,lvl1`` serves the loops named; ``--shard K/N`` the K-th of N shares, dealt
round-robin in the file's order (loops 1, N+1, 2N+1, … of the file go to shard 1): every
loop of the file is in exactly one of the N shards whatever its id, and no shard of a file
of at least N loops is empty. The per-loop keys do not change, so the tuner, the logger and
the CLI find each loop wherever it is served.

Two processes serving the same loop under one prefix would both apply its commands and both
publish its samples. A plant process therefore asks, before it takes any command, every
plant process under its prefix which loops it serves (their ``ServiceStatus``, its own
included, for its queryable is declared first) and refuses to start if another serves one of
its loops: one line naming them, exit 2. Two processes started at the same moment may both
see each other and both refuse, or miss each other (neither's claim yet reached the other:
3 tries in 10 over a router, 9–125 ms apart); each also watches the other plant processes'
instance tokens for as long as it serves (``PlantService._on_plant``), and of two found
serving one loop the later started stops (exit 2, naming the other).
"""

from __future__ import annotations

import re

import zenoh

from shared import keys, wire
from shared.errors import ConfigError
from shared.messages import ServiceStatus

_SHARD = re.compile(r"^([0-9]+)/([0-9]+)$")
CLAIM_TIMEOUT = 5.0  # s: the longest wait for the other plant processes to say what they serve


def parse_shard(text: str) -> tuple[int, int]:
    """``K/N`` → (K, N), 1 ≤ K ≤ N; ConfigError naming the flag otherwise."""
    m = _SHARD.match(text.strip())
    if m is None or not 1 <= int(m.group(1)) <= int(m.group(2)):
        raise ConfigError(f"--shard {text!r}: expected K/N with 1 ≤ K ≤ N, e.g. 1/2")
    return int(m.group(1)), int(m.group(2))


def parse_loop_list(text: str) -> list[str]:
    """``hx1,lvl1`` → the ids, in order, each once; ConfigError naming the flag otherwise."""
    ids = [part.strip() for part in text.split(",")]
    if not text.strip() or any(not i for i in ids):
        raise ConfigError(f"--loops {text!r}: expected loop ids separated by commas")
    twice = sorted({i for i in ids if ids.count(i) > 1})
    if twice:
        raise ConfigError(f"--loops {text!r}: {', '.join(twice)} named more than once")
    return ids


def select_loops(file_ids: list[str], loops: str | None, shard: str | None) -> list[str]:
    """The ids this process serves out of the file's (in file order)."""
    if loops is not None and shard is not None:
        raise ConfigError("--loops and --shard: give one of them, not both")
    if loops is not None:
        wanted = parse_loop_list(loops)
        missing = [i for i in wanted if i not in file_ids]
        if missing:
            raise ConfigError(
                f"--loops: {', '.join(missing)} not in the plant file (it has {_some(file_ids)})"
            )
        return [i for i in file_ids if i in set(wanted)]
    if shard is not None:
        k, n = parse_shard(shard)
        mine = file_ids[k - 1 :: n]
        if not mine:
            raise ConfigError(
                f"--shard {shard}: the plant file has {len(file_ids)} loop(s), none for shard {k}"
            )
        return mine
    return list(file_ids)


def _some(ids: list[str], limit: int = 8) -> str:
    shown = ", ".join(ids[:limit])
    return shown + (f", … ({len(ids)} in all)" if len(ids) > limit else "")


def served_elsewhere(
    session: zenoh.Session, prefix: str, mine: set[str], timeout: float = CLAIM_TIMEOUT
) -> list[str]:
    """The loops of ``mine`` that another plant process under ``prefix`` serves (sorted).

    Every plant's ServiceStatus answers, this process's own among them (its queryable must
    be declared already): a loop is served elsewhere when more than one answer lists it.
    """
    counts: dict[str, int] = {}
    key = keys.service_status(prefix, "plant_sim", keys.ANY)
    # a malformed answer is no claim on our loops (query_all leaves it out)
    for st in wire.query_all(session, key, ServiceStatus, timeout):
        for lid in mine.intersection(st.loops):
            counts[lid] = counts.get(lid, 0) + 1
    return sorted(lid for lid, c in counts.items() if c > 1)


def check_not_served(session: zenoh.Session, prefix: str, mine: set[str]) -> None:
    """ConfigError (one line) when another plant process serves one of ``mine``."""
    both = served_elsewhere(session, prefix, mine)
    if both:
        raise ConfigError(
            f"loop(s) {_some(both)} already served by another plant process under prefix "
            f"{prefix!r}: each loop must be served by one process (split the plant file "
            "with --loops or --shard K/N)"
        )
