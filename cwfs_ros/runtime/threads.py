"""One BLAS thread per process, set by the entry points (the worker initialiser forces it).

The linear algebra here is small (<= 15k x 120); BLAS threads only fight with the per-corner
worker processes and make every call slower on a busy machine (measured: a 5k x 120 lstsq
took 1.8 s with OpenBLAS's two threads, 0.03 s with one). Importing the library changes
nothing: a program that embeds it keeps its own BLAS settings; the ``cwfs-ros`` command, the
nodes, the tests and the benchmarks call :func:`limit_blas_threads`.
"""

from __future__ import annotations

import os
import sys

__all__ = ["BLAS_THREAD_VARIABLES", "limit_blas_threads"]

BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads() -> None:
    """Limit BLAS to one thread in this process and its children, unless the user chose.

    A user's own setting of any of :data:`BLAS_THREAD_VARIABLES` wins. Otherwise the variables
    are set (for a numpy not yet loaded, and for child processes) and, if numpy is already
    loaded, threadpoolctl applies the limit to the loaded BLAS.
    """
    if any(v in os.environ for v in BLAS_THREAD_VARIABLES):
        return
    for var in BLAS_THREAD_VARIABLES:
        os.environ[var] = "1"
    if "numpy" in sys.modules:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1, user_api="blas")
