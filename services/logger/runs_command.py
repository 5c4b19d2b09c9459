"""``autotune runs [DIR]``: list the recorded runs (time, loop, method, K_u, P_u, rule, gains,
status), newest last."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.logger.mcap_io import read_run
from shared.errors import AutotuneError

HELP = "list the recorded tuning runs"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "runs",
        nargs="?",
        default="runs",
        metavar="DIR",
        help="the logger's runs directory (default: %(default)s)",
    )
    parser.add_argument("--json", action="store_true", help="one JSON object per run, a list")


def summarize(path: Path) -> dict:
    try:
        meta, _ = read_run(path)
    except AutotuneError as err:
        return {"file": path.name, "status": "unreadable", "reason": str(err).split(" (")[0]}
    result = json.loads(meta["result"]) if meta.get("result") else {}
    chosen = (result.get("chosen") or {}).get("isa")
    return {
        "file": path.name,
        "started": meta.get("started"),
        "loop": meta.get("loop"),
        "method": meta.get("method"),
        "rule": meta.get("rule"),
        "ku": result.get("ku"),
        "pu": result.get("pu"),
        "gains": chosen,
        "status": meta.get("status"),
        "samples": int(meta.get("samples") or 0),
        "dropped": int(meta.get("dropped") or 0),
    }


def _num(v, fmt: str = ".4g") -> str:
    return "—" if v is None else format(v, fmt)


def run(args: argparse.Namespace) -> int:
    folder = Path(args.runs)
    if not folder.is_dir():
        raise AutotuneError(f"{folder}: no such directory (the logger's --runs)")
    rows = [summarize(p) for p in sorted(folder.glob("*.mcap"))]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    if not rows:
        print(f"no runs in {folder}")
        return 0
    print(
        f"{'started (UTC)':<20} {'loop':<8} {'method':<6} {'K_u':>9} {'P_u (s)':>9} "
        f"{'rule':<12} {'Kc':>8} {'Ti':>8} {'Td':>8} status"
    )
    for r in rows:
        g = r.get("gains") or {}
        print(
            f"{(r.get('started') or '')[:19]:<20} {r.get('loop') or '':<8} "
            f"{r.get('method') or '':<6} {_num(r.get('ku')):>9} {_num(r.get('pu')):>9} "
            f"{r.get('rule') or '':<12} {_num(g.get('kc')):>8} {_num(g.get('ti')):>8} "
            f"{_num(g.get('td')):>8} {r['status']}  {r['file']}"
        )
    return 0
