"""Accuracy targets of a reduced model at held-out tool positions: the one place they live.

``hapticrom accuracy`` (:mod:`hapticrom.offline.accuracy`) measures the errors and states
these targets with a verdict; ``hapticrom report`` states the same ones. Pure Python: the
report runs wherever the online runtime runs, without the finite-element stack.

A *combination* is ``"<interpolation>+<response>"`` (``"podi+anm"``, ``"grassmann+curves"``);
its targets depend on the response only. Errors are fractions (0.02 is 2 %):

- force: the largest relative error of the normal force on the tool, over every load step
  of every held-out position: 5 % for the interpolated full-order curves (issue "artifact
  and online runtime"), 2 % for the POD-ANM series (issue "POD-ANM");
- field: the largest relative L2 error of the surface displacement (over the surface
  vertices, all three components), over the same steps: 3 % (issue 15).
"""

from __future__ import annotations

import math

FORCE_TARGETS = {"curves": 0.05, "anm": 0.02}
FIELD_TARGET = 0.03
TARGETS = {
    "force": FORCE_TARGETS,
    "field": {response: FIELD_TARGET for response in FORCE_TARGETS},
}
QUANTITIES = {
    "force": "normal force, max relative error",
    "field": "surface displacement, max relative L2 error",
}


def target(quantity: str, combination: str) -> float | None:
    """The target (a fraction) of ``quantity`` ("force" or "field") for a combination."""
    return TARGETS[quantity].get(combination.split("+")[-1])


def verdict(error: float, limit: float | None) -> str:
    """ "met", "missed", "not measured" (a NaN error) or "" (no target)."""
    if limit is None:
        return ""
    if not math.isfinite(error):
        return "not measured"
    return "met" if error <= limit else "missed"
