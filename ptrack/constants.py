"""Physical constants (CODATA 2018 exact SI values where defined)."""

BOLTZMANN = 1.380649e-23          # J/K, exact
ELEMENTARY_CHARGE = 1.602176634e-19  # C, exact
AVOGADRO = 6.02214076e23          # 1/mol, exact
VACUUM_PERMITTIVITY = 8.8541878128e-12  # F/m
STANDARD_GRAVITY = 9.80665        # m/s^2

#: largest motion-blur parameter accepted (exclusive). R = S/6 for a uniform exposure of a fraction S of the
#: frame, so a real camera has R <= 1/6; R = 1/4 would need all the light at the two ends of the frame and makes
#: the increments' covariance singular without localisation noise (velocity GLS, CVE error model).
MOTION_BLUR_MAX = 0.25
