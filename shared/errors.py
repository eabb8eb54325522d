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


# -- the online runtime's errors: one family under SimulatorError ----------------------------
class SimulatorError(HapticromError):
    """Base class of the errors the online runtime raises while it runs (a simulator's
    inputs, its threading contract, its use before a contact); the state is unchanged."""


class StepInputError(SimulatorError, ValueError):
    """A step input was of a wrong shape, not numbers, NaN, infinite or absurd; the
    simulator state is unchanged."""


class ScalpelInputError(SimulatorError, ValueError):
    """A scalpel position off the organ or a degenerate blade; the cut state is unchanged."""


class SimulatorBusyError(SimulatorError, RuntimeError):
    """Another thread is inside this simulator: one simulator, one thread at a time."""


class NoContactError(SimulatorError, RuntimeError):
    """A step before any contact: call ``set_contact(point)`` (or ``scalpel``) first."""


class OutputArrayError(SimulatorError, ValueError):
    """An array passed to receive an output (``surface_displacement(out)``) has the wrong
    shape, dtype or memory layout."""
