"""The Morpheus3D method: tensors in, tensors out. Imports neither Dagster nor the store."""

import os

# MKL (torch's CPU BLAS) picks its code path per process unless told to keep one, so the same float
# computation could round differently in two processes on one machine: the DMTet stage's NeRF → SDF
# conversion did in 1 of 8 fresh processes, and a resumed run then no longer matched an uninterrupted
# one bit for bit. "AUTO" keeps the path MKL would choose, fixed run to run (0 of 40 differed). It is
# read at MKL's first call, so setting it here, before any computation, is enough; a value set by the
# user wins.
os.environ.setdefault("MKL_CBWR", "AUTO")
