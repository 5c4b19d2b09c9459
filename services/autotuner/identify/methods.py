"""The registry of experiments: a method's name → how to build it and what it needs and gives.

Adding a method: its module (an ``Experiment`` with a ``build(settings, setup)``), one entry
here, and its name among the CLI's and the request's choices.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from services.autotuner.identify import ramp, relay, repeated_steps
from services.autotuner.identify.experiments import Experiment, Settings, Setup


@dataclass(frozen=True)
class Method:
    """How to run one method."""

    build: Callable[[Settings, Setup], Experiment]
    # True: it runs the loop in auto, P-only (the set-up gives kc_start, bump and sp_start);
    # False: in manual at op_start (the set-up gives op_start and direction)
    closed_loop: bool
    needs: tuple[str, ...]  # the set-up's fields it cannot do without
    # the kinds of rule its identification supports (``rules.Rule.kind``): "closed" (K_u and
    # P_u), "open" (a reaction curve), "model" (a process model)
    gives: frozenset[str]


METHODS: dict[str, Method] = {
    "relay": Method(relay.build, False, ("op_start", "direction"), frozenset({"closed", "model"})),
    # the ramp's model (fitted to its whole record, when the fit holds) is what its own
    # recommendation designs model rules from: asked for by name, or approved by
    # `autotune apply`, they are the same rules (refused with the reason where no model fits)
    "ramp": Method(
        ramp.build, True, ("kc_start", "bump", "sp_start"), frozenset({"closed", "model"})
    ),
    "step": Method(repeated_steps.build, False, ("op_start",), frozenset({"open", "model"})),
}


def method(name: str) -> Method:
    """The registered method; ValueError naming it if there is none."""
    try:
        return METHODS[name]
    except KeyError:
        raise ValueError(f"method: unknown method {name!r}") from None


def build(name: str, settings: Settings, setup: Setup) -> Experiment:
    """The state machine for method ``name``; ValueError naming the setting that cannot work."""
    return method(name).build(settings, setup)
