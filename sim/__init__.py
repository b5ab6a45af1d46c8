"""sim: discrete-element / Langevin simulator of charged colloids driven by an
electric field through a fluid onto a substrate, its verification studies, and
a synthetic-microscope renderer. SI units throughout."""

import os as _os

# numba's OpenMP threading layer (libgomp) reads its wait policy once, when it is loaded, and importing
# sim.dem loads it.  Its default spins an idle thread for 300 000 turns before it sleeps; on a machine where
# any other process shares a core, a threaded DEM run then stalls at every parallel region, often past the
# time of one thread.  A short spin keeps the fast hand-over between regions without that stall (README,
# "DEM on 2 threads").  An explicit GOMP_SPINCOUNT or OMP_WAIT_POLICY is left alone.
OPENMP_SPIN = "10000"
openmp_spin_set = "GOMP_SPINCOUNT" not in _os.environ and "OMP_WAIT_POLICY" not in _os.environ
if openmp_spin_set:
    _os.environ["GOMP_SPINCOUNT"] = OPENMP_SPIN

import ptrack  # noqa: E402,F401  (registers the dependency-aware numba cache stamp before any kernel)
