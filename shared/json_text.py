"""JSON text for people's tools: what every ``--json`` prints, and the console's messages.

Python's ``json`` writes a float that is not finite as ``Infinity`` or ``NaN``, which is not
JSON: ``jq`` and every strict parser refuse the whole output (``autotune analyze --json``
printed ``"ku_describing_function": Infinity`` for a relay cycle inside its hysteresis). A
figure that is not finite is not known, so it goes out as ``null``, the same as the bus's
messages carry it.
"""

from __future__ import annotations

import json
import math
from typing import Any


def finite(x: Any) -> Any:
    """``x`` with every float that is not finite, at any depth, replaced by None."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [finite(v) for v in x]
    return x


def loads(text: str | bytes) -> Any:
    """``json.loads`` of text from outside (the bus, a file, a browser): JSONDecodeError (a
    ValueError) for anything that is not JSON it can read, a nesting too deep included
    (``json`` raises RecursionError there: an attachment of 100,000 ``[`` put a traceback in
    the logger's and the tuner's logs for every message, uncounted)."""
    try:
        return json.loads(text)
    except RecursionError:
        raise json.JSONDecodeError("nested too deeply to read", "", 0) from None


def dumps(obj: Any, **kw: Any) -> str:
    """``json.dumps`` of ``finite(obj)``: strict JSON whatever the figures."""
    return json.dumps(finite(obj), allow_nan=False, **kw)
