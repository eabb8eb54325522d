"""numba's allocation counters, for the tests that a compiled kernel allocates nothing.

A probe is a script run in a fresh interpreter with NUMBA_NRT_STATS=1. Its prologue
checks that the counters see an allocating canary, and defines ``same_allocations(run,
*arguments)``: a compiled driver ``run(*arguments, n)`` moves the counters as much over
n = 1000 calls as over one (the boxing of its arguments only). ``BLOCK_FE_STACK`` is a
preamble that makes the finite-element stack and scipy unimportable first (the runtime
must not need them); the probe's body ends by printing "ok".
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

BLOCK_FE_STACK = """
import sys, importlib.abc
class _Block(importlib.abc.MetaPathFinder):
    BLOCKED = ("scipy", "dolfinx", "petsc4py", "slepc4py", "mpi4py", "ufl", "gmsh",
               "matplotlib", "basix", "ffcx")
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in self.BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, _Block())
"""

PROLOGUE = """
import numpy as np
from numba import njit
from numba.core.runtime import rtsys

@njit
def allocating(n):  # the counters' canary: one array per iteration
    total = 0.0
    for _ in range(n):
        total += np.ones(3)[0]
    return total

allocating(1)
_before = rtsys.get_allocation_stats().alloc
allocating(100)
assert rtsys.get_allocation_stats().alloc - _before == 100

def same_allocations(run, *arguments):
    run(*arguments, 1)  # compile the driver
    before = rtsys.get_allocation_stats()
    run(*arguments, 1)
    once = rtsys.get_allocation_stats()
    run(*arguments, 1000)
    after = rtsys.get_allocation_stats()
    per_call = [b - a for a, b in zip(before, once)]  # the arguments' boxing only
    assert [b - a for a, b in zip(once, after)] == per_call, (before, once, after)
"""


def run_probe(body: str, preamble: str = "", env: dict | None = None) -> None:
    """Run ``preamble``, the prologue and ``body`` (dedented) in a fresh interpreter; fail
    unless it exits 0 having printed "ok" last."""
    code = preamble + PROLOGUE + textwrap.dedent(body)
    environment = {**os.environ, **(env or {}), "NUMBA_NRT_STATS": "1"}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=environment, timeout=900)  # fmt: skip
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-3000:]
