"""sim: discrete-element / Langevin simulator of charged colloids driven by an
electric field through a fluid onto a substrate, its verification studies, and
a synthetic-microscope renderer. SI units throughout."""

import ptrack  # noqa: E402,F401  (registers the dependency-aware numba cache stamp before any kernel)
