"""Watching a loop in normal operation, no test signal: the pure core of ``autotune watch`` and
of the tuner's monitor (``<prefix>/monitor/<loop>``).

``performance``: the figures over a window of samples (IAE per unit time, the error's s.d.,
output saturation, travel and reversals); ``oscillation``: Hägglund's detector (the IAE between
zero crossings of the control error against a limit set from the ultimate period); ``idle_index``:
Hägglund's index of sluggish control; ``assessment``: a streaming ``Watcher`` that feeds them
sample by sample and reports a window's figures and flags (oscillating, sluggish, saturated,
degraded) with their reasons, compared with the last tune's verification. numpy only: the same
code runs live (the tuner, ``watch``) and offline (the tests).
"""
