"""Curvature wavefront sensing, as in Xin et al. 2015 (Applied Optics 54, 9045).

One module per part of the paper's algorithm (its Fig. 3):

* :mod:`.zernike`: the annular Zernike basis (Noll order);
* :mod:`.instrument`: the telescope and sensor geometry from ``config/instruments``;
* :mod:`.mapping`: pupil-to-image mappings (fast f-number, off-axis distortion and
  vignetting: Secs. 3.2-3.3);
* :mod:`.donuts` and :mod:`.checks`: stamp preparation and input checks;
* :mod:`.compensation` and :mod:`.blur`: the outer loop's image compensation (Sec. 2.1) and
  the seeing reference;
* :mod:`.tie`: the TIE solvers (iterative FFT: Sec. 2.1; series expansion: Sec. 2.2);
* :mod:`.estimator`: the algorithm, :func:`estimate_wavefront`;
* :mod:`.settings`: the estimator settings shared by the live and offline paths;
* :mod:`.orientation`: image orientation into the focal-plane frame; :mod:`.io`: files.

No ROS import anywhere in this package.
"""

from cwfs_ros.wfs.estimator import WavefrontResult, estimate_wavefront
from cwfs_ros.wfs.instrument import Instrument, load_instrument
from cwfs_ros.wfs.orientation import Orientation, orient_image
from cwfs_ros.wfs.settings import EstimatorSettings, validate_settings

__all__ = ["EstimatorSettings", "Instrument", "Orientation", "WavefrontResult",
           "estimate_wavefront", "load_instrument", "orient_image", "validate_settings"]
