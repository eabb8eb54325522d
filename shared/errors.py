"""Exception types shared by every part of hapticrom.

The CLI prints a :class:`HapticromError` as one line (``error: ...``) and
exits with status 2; anything else is a bug and keeps its traceback.
"""


class HapticromError(Exception):
    """Base class of the errors a user can cause and fix."""


class InputError(HapticromError, ValueError):
    """A configuration, a mesh or a parameter is wrong; the message says which."""


class SolverError(HapticromError, RuntimeError):
    """A solve did not converge even after cutting the load step to its floor."""


class ArtifactError(HapticromError):
    """A file is not a valid hapticrom artifact; the message names the problem."""
