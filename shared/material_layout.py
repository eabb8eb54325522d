"""The packed material parameters both sides agree on: one float64 row per element, the
layout named once (the runtime's laws, :mod:`hapticrom.online.material_kernels`, read it;
the trainer writes it into the artifact's ``hyperreduced`` group), and the rule a row must
satisfy before a law may read it (:func:`packed_problem`). numpy only."""

from __future__ import annotations

import numpy as np

LAW_SVK, LAW_NEO_HOOKEAN, LAW_HGO = 0, 1, 2
LAW_IDS = {"svk": LAW_SVK, "neo-hookean": LAW_NEO_HOOKEAN, "hgo": LAW_HGO}

# -- offsets into the row ----------------------------------------------------------------------
LAW = 0  # the law's id (LAW_SVK, LAW_NEO_HOOKEAN, LAW_HGO) as a float
KAPPA = 1  # modulus of the volumetric term kappa/2 theta^2 (MPa): lambda, or 2/D for hgo
MU = 2  # svk, neo-hookean: the shear modulus mu (MPa)
C1 = 2  # hgo: C1 (MPa) of C1/2 (I1b - 3)
C2 = 3  # hgo: C2 (MPa) of C2/2 (I2b - 3)
K1, K2 = 4, 5  # hgo: stiffness (MPa) and exponent (-) of the m0 family
K3, K4 = 6, 7  # hgo: stiffness (MPa) and exponent (-) of the n0 family
M0 = 8  # hgo: (3) unit direction of the first fibre family (reference configuration)
N0 = 11  # hgo: (3) unit direction of the second fibre family
TENSION_ONLY = 14  # hgo: 1.0 if a fibre family carries nothing while not stretched (I4b <= 1)
PARAMETER_SIZE = 15
UNIT_TOLERANCE = 1e-6  # how far |m0|, |n0| may be from 1

# Bounds no tissue comes near (soft tissue: kPa to a few MPa; the cornea's kappa 2e5 MPa,
# its fibre exponent 30): past them a row is absurd, and exp(k2 (I4 - 1)^2) overflows at
# strains a haptic model reaches.
MAX_MODULUS = 1e9  # MPa
MAX_EXPONENT = 1e3


def packed_problem(rows: np.ndarray) -> str | None:
    """What is wrong with the first bad row of ``rows`` (R, PARAMETER_SIZE), or None: a law
    id the runtime knows; kappa and the shear modulus (svk, neo-hookean) or C1 (hgo)
    positive, hgo's C2, k1, k3 not negative and its exponents positive, all within the
    bounds above; hgo's fibres unit vectors and its tension flag 0 or 1; every entry a law
    does not read zero."""
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != PARAMETER_SIZE:
        return f"must be (rows, {PARAMETER_SIZE}), not {rows.shape}"
    for r, row in enumerate(rows):
        problem = _row_problem(row)
        if problem:
            return f"row {r}: {problem}"
    return None


def _row_problem(row: np.ndarray) -> str | None:
    if not np.isfinite(row).all():
        return "not finite"
    if row[LAW] not in (LAW_SVK, LAW_NEO_HOOKEAN, LAW_HGO):
        return f"unknown law id {row[LAW]!r}"
    if not 0 < row[KAPPA] <= MAX_MODULUS:
        return f"kappa {row[KAPPA]!r} MPa outside (0, {MAX_MODULUS:g}]"
    if row[LAW] != LAW_HGO:
        unused = np.delete(row, [LAW, KAPPA, MU])
        if not 0 < row[MU] <= MAX_MODULUS:
            return f"mu {row[MU]!r} MPa outside (0, {MAX_MODULUS:g}]"
        return "an entry the law does not read is not zero" if np.any(unused) else None
    if not 0 < row[C1] <= MAX_MODULUS:
        return f"C1 {row[C1]!r} MPa outside (0, {MAX_MODULUS:g}]"
    for name, k in (("C2", C2), ("k1", K1), ("k3", K3)):
        if not 0 <= row[k] <= MAX_MODULUS:
            return f"{name} {row[k]!r} MPa outside [0, {MAX_MODULUS:g}]"
    for name, k in (("k2", K2), ("k4", K4)):
        if not 0 < row[k] <= MAX_EXPONENT:
            return f"{name} {row[k]!r} outside (0, {MAX_EXPONENT:g}]"
    for name, k in (("m0", M0), ("n0", N0)):
        if abs(np.linalg.norm(row[k : k + 3]) - 1) > UNIT_TOLERANCE:
            return f"{name} is not a unit vector"
    if row[TENSION_ONLY] not in (0.0, 1.0):
        return f"the tension-only flag is {row[TENSION_ONLY]!r}, not 0 or 1"
    return None
