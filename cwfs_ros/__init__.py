"""cwfs_ros: curvature wavefront sensing and active-optics control for wide-field telescopes.

The science lives in :mod:`cwfs_ros.core` (no ROS imports); the ROS 2 nodes are thin wrappers.
"""

import os as _os
import sys as _sys

# The linear algebra here is small (<= 15k x 120); BLAS threads only fight with the
# per-corner worker processes and make every call slower on a busy machine (measured: a
# 5k x 120 lstsq took 1.8 s with OpenBLAS's two threads, 0.03 s with one).  Before numpy
# loads, the environment does it; if numpy is already loaded, threadpoolctl does.  A user's
# own setting of these variables wins.
_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
if not any(v in _os.environ for v in _VARS):
    for _var in _VARS:
        _os.environ[_var] = "1"
    if "numpy" in _sys.modules:
        from threadpoolctl import threadpool_limits as _limits

        _limits(limits=1, user_api="blas")

__version__ = "0.1.0"
