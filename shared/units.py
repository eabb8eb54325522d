"""Unit system of hapticrom: millimetre, newton, megapascal (N/mm^2).

The system is consistent: stresses and moduli in MPa = N/mm^2, forces in N,
lengths and displacements in mm, energies in mJ (N mm), energy densities in
MPa (mJ/mm^3). Every file hapticrom writes states its units with these names.
"""

LENGTH = "mm"
FORCE = "N"
STRESS = "MPa"
ENERGY = "mJ"

UNITS = {"length": LENGTH, "force": FORCE, "stress": STRESS, "energy": ENERGY}
