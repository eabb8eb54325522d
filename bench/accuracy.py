"""Accuracy of the reduced model at held-out tool positions: now ``hapticrom accuracy``.

    mpirun -n 2 python bench/accuracy.py out/cornea.h5 [--positions 8] [--seed S] [--work DIR]
        [--json FILE]

is the same as ``mpirun -n 2 hapticrom accuracy ...`` (kept for old scripts): full-order
solves at held-out positions, force and surface-field errors against the targets of
``hapticrom.shared.accuracy``, with verdicts. See ``hapticrom accuracy --help`` and
``hapticrom/offline/accuracy.py``.
"""

from __future__ import annotations

import sys

from hapticrom.cli import main

if __name__ == "__main__":
    sys.exit(main(["accuracy", *sys.argv[1:]]))
