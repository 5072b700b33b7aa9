"""Core library: curvature wavefront estimation (no ROS imports).

Modules follow the paper (Xin et al. 2015) and the optics: :mod:`.zernike` (annular basis),
:mod:`.instrument` (geometry from ``config/``), :mod:`.mapping` (pupil-to-image models),
:mod:`.donuts` (stamp preparation), :mod:`.compensation` (outer-loop image remapping),
:mod:`.tie` (the two TIE solvers), :mod:`.estimator` (the algorithm), :mod:`.io` (files).
"""

from cwfs_ros.errors import ConfigError, CwfsError, ImageError
from cwfs_ros.wfs.estimator import WavefrontResult, estimate_wavefront
from cwfs_ros.wfs.instrument import Instrument, load_instrument

__all__ = ["estimate_wavefront", "WavefrontResult", "Instrument", "load_instrument",
           "CwfsError", "ConfigError", "ImageError"]
