"""One BLAS thread in each slcp process; imported by the command line before numpy loads.

slcp runs a process per vehicle (and a pool worker per seed), each multiplying matrices of a few
dozen rows. OpenBLAS's default of a worker thread per core buys nothing at that size and costs
twice: the threads start with every process, and after a call they share they spin waiting for
the next, on the cores the fleet's other processes need. The processes a command starts inherit
the setting from the environment. A value the user set is kept.
"""

from __future__ import annotations

import os

#: the thread-count variables of OpenBLAS (numpy's wheels), OpenMP builds and MKL
VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")

for _name in VARIABLES:
    os.environ.setdefault(_name, "1")
