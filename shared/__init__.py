"""What the offline trainer and the online runtime must agree on.

Pure Python and numpy only: the error types, the unit conventions and (with
the artifact issue) the on-disk schema of a reduced model.
"""

from hapticrom.shared.errors import HapticromError, InputError, SolverError

__all__ = ["HapticromError", "InputError", "SolverError"]
