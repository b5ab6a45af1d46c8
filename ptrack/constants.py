"""Physical constants (CODATA 2018 exact SI values where defined)."""

BOLTZMANN = 1.380649e-23          # J/K, exact
ELEMENTARY_CHARGE = 1.602176634e-19  # C, exact
AVOGADRO = 6.02214076e23          # 1/mol, exact
VACUUM_PERMITTIVITY = 8.8541878128e-12  # F/m
STANDARD_GRAVITY = 9.80665        # m/s^2
