"""Photon-tracing simulator of the perturbed Rubin/LSST telescope and its corner sensors.

Pure Python (no ROS imports). It is independent of the wavefront estimator in
:mod:`cwfs_ros.core`: donuts are made by tracing rays through batoid's full optical model,
not by a pupil-to-image mapping, so closed-loop tests are not an inverse crime.

* :mod:`cwfs_ros.sim.telescope`: nominal and DoF-perturbed LSST models and the defocused
  detector.
* :mod:`cwfs_ros.sim.render`: donut rendering, vignetting, true Zernikes, and the
  corner-sensor geometry.
"""

from cwfs_ros.sim.render import (
    CornerSensor,
    RenderSettings,
    TracedRays,
    camera_zernikes_nm,
    corner_fields,
    load_corner_geometry,
    plate_scale_um_per_arcsec,
    pupil_vignetting_fraction,
    render_donut,
    trace_pupil_rays,
    true_zernikes_nm,
)
from cwfs_ros.sim.telescope import (
    BANDS,
    CONVENTIONS,
    DOF_NAMES,
    DOF_UNITS,
    N_DOF,
    TS_OFC_FLIPPED_DOF,
    bending_zernikes,
    defocused,
    load_lsst,
    perturbed_telescope,
)

__all__ = [
    "BANDS",
    "CONVENTIONS",
    "DOF_NAMES",
    "DOF_UNITS",
    "N_DOF",
    "TS_OFC_FLIPPED_DOF",
    "CornerSensor",
    "RenderSettings",
    "TracedRays",
    "bending_zernikes",
    "camera_zernikes_nm",
    "corner_fields",
    "defocused",
    "load_corner_geometry",
    "load_lsst",
    "perturbed_telescope",
    "plate_scale_um_per_arcsec",
    "pupil_vignetting_fraction",
    "render_donut",
    "trace_pupil_rays",
    "true_zernikes_nm",
]
