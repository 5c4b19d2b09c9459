"""The registry of experiments: a method's name → how to build it and what it needs and gives.

Adding a method: its module (an ``Experiment`` with a ``build(settings, setup)``), one entry
here, and its name among the CLI's and the request's choices.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

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


def _built_by(module: str) -> Callable[[Settings, Setup], Experiment]:
    """The ``build`` of the experiment in ``module`` (of this package), imported when it is
    first built. Why: the registry is read wherever a request is checked (``autotune tune``
    and ``apply`` check theirs before sending), and the experiments' fits import scipy's
    optimisers, half a second of every such command's start."""

    def build(settings: Settings, setup: Setup) -> Experiment:
        return importlib.import_module(f"{__package__}.{module}").build(settings, setup)

    return build


METHODS: dict[str, Method] = {
    "relay": Method(
        _built_by("relay"), False, ("op_start", "direction"), frozenset({"closed", "model"})
    ),
    # the ramp's model (fitted to its whole record, when the fit holds) is what its own
    # recommendation designs model rules from: asked for by name, or approved by
    # `autotune apply`, they are the same rules (refused with the reason where no model fits)
    "ramp": Method(
        _built_by("ramp"), True, ("kc_start", "bump", "sp_start"), frozenset({"closed", "model"})
    ),
    "step": Method(_built_by("repeated_steps"), False, ("op_start",), frozenset({"open", "model"})),
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
