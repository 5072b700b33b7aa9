"""The stable entry point of the estimator: ``from cwfs_ros.core import estimate_wavefront``.

A documented re-export kept for scripts written against it; the estimator itself is
:mod:`cwfs_ros.wfs` (the paper's modules), the package's layout is in docs/design.md.
"""

from cwfs_ros.errors import ConfigError, CwfsError, ImageError
from cwfs_ros.wfs.estimator import WavefrontResult, estimate_wavefront
from cwfs_ros.wfs.instrument import Instrument, load_instrument

__all__ = ["estimate_wavefront", "WavefrontResult", "Instrument", "load_instrument",
           "CwfsError", "ConfigError", "ImageError"]
