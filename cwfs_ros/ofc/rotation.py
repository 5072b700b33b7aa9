"""The camera rotator: turning camera-frame measurements into the telescope frame (no ROS).

Convention (batoid_rubin's ``LSSTBuilder.with_rtp``)
----------------------------------------------------
The camera rotated by ``angle`` is ``telescope.withLocallyRotatedOptic("LSSTCamera",
batoid.RotZ(angle))``, applied to the nominal telescope *before* the rigid-body DoF (as
:func:`cwfs_ros.sim.telescope.perturbed_telescope` does with ``rotator_angle_deg``).
``batoid.RotZ(a)`` is ``[[cos a, -sin a, 0], [sin a, cos a, 0], [0, 0, 1]]``: it maps the
camera's local axes to batoid's global (telescope) axes, so a positive angle turns the camera
counter-clockwise as seen along the telescope's +z (towards the focal plane).

Frames
------
* **Telescope frame:** batoid's global x, y (field angles ``theta_x, theta_y`` and the
  entrance-pupil coordinates of ``batoid.zernike``).
* **Camera frame:** the rotated camera's own (detector-local) x, y. The images arrive in it,
  the wavefront estimator works in it, and a corner sensor's nominal field point
  (``config/sensors/lsst_corners.yaml``) is given in it. At angle 0 the two frames coincide.

What lives where (DoF in ts_ofc order, batoid_rubin signs, as ``DofCorrection`` carries them)
------------------------------------------------------------------------------------------
* M2 hexapod (0-4): telescope frame.
* camera hexapod dz, dx, dy (5-7): telescope frame (batoid_rubin applies them as global shifts,
  after the rotation).
* camera hexapod rx, ry (8, 9): **camera frame** (batoid_rubin applies them as a local
  rotation of the already rotated camera, so they turn about the rotated camera's axes).
* bending modes (10-49): telescope frame (M1M3 and M2 do not rotate with the camera).

Relations (checked with batoid in ``test/test_rotation.py``)
------------------------------------------------------------
For a DoF vector ``x`` applied to the rotated telescope, a camera-frame field point ``f`` and
the camera-frame Zernikes ``z_cam`` that the rotated camera measures there::

    z_tel = zernike_rotation_matrix(angle) @ z_cam
          = Zernikes of the UNROTATED telescope with DoF dof_rotation_matrix(angle) @ x,
            at the telescope field telescope_field_deg(f, angle).

That holds because the camera optics are axisymmetric: the rotated camera tilted about its own
axes equals the unrotated camera tilted by the rotated tilt, then turned about its (tilted)
axis, which changes nothing optically but the detector's x, y.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from cwfs_ros.layout import N_DOF

__all__ = [
    "CAMERA_FRAME_DOF",
    "dof_rotation_matrix",
    "noll_to_nm",
    "rotation_2d",
    "telescope_field_deg",
    "zernike_rotation_matrix",
]

#: DoF that live in the camera frame: the camera hexapod's rx, ry (8, 9).
CAMERA_FRAME_DOF: tuple[int, int] = (8, 9)


def rotation_2d(angle_rad: float) -> np.ndarray:
    """``[[cos, -sin], [sin, cos]]``: the x, y block of ``batoid.RotZ(angle_rad)``."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s], [s, c]])


def telescope_field_deg(field_camera_deg: np.ndarray | Sequence[float],
                        angle_rad: float) -> np.ndarray:
    """Telescope-frame field angles seen by camera-frame field points.

    Parameters
    ----------
    field_camera_deg : (n, 2) or (2,) field points ``(x, y)`` [deg] in the camera frame (a
        sensor's nominal field, where it sits on the unrotated focal plane).
    angle_rad : rotator angle [rad], the argument of ``batoid.RotZ``.

    Returns
    -------
    (n, 2) array [deg]: ``R(angle) @ f`` for each point, ``R`` of :func:`rotation_2d`. The
    chief ray of that telescope field lands on the rotated detector where ``f`` lands on the
    unrotated one.
    """
    f = np.asarray(field_camera_deg, dtype=np.float64).reshape(-1, 2)
    return f @ rotation_2d(angle_rad).T


def noll_to_nm(j: int) -> tuple[int, int]:
    """Radial order ``n`` and signed azimuthal order ``m`` of Noll index ``j >= 1``.

    ``m > 0`` is a ``cos(m phi)`` term, ``m < 0`` a ``sin(|m| phi)`` term, ``m = 0`` radial
    only. Noll's rule: for ``m != 0`` an even ``j`` is the cosine, an odd ``j`` the sine.
    """
    if j < 1:
        raise ValueError(f"Noll index must be >= 1, got {j}")
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    p = j - n * (n + 1) // 2 - 1  # 0-based position within radial order n
    ms = [0] if n % 2 == 0 else []
    for m in range(2 - n % 2, n + 1, 2):
        ms += [m, m]
    m = ms[p]
    return n, (m if m == 0 or j % 2 == 0 else -m)


def zernike_rotation_matrix(angle_rad: float, noll_min: int = 4,
                            noll_max: int = 22) -> np.ndarray:
    """Map Noll Zernike coefficients measured in the camera frame to the telescope frame.

    Parameters
    ----------
    angle_rad : rotator angle [rad] (``batoid.RotZ`` argument).
    noll_min, noll_max : the Noll range of the coefficient vectors (default Z4..Z22, 19 terms).
        Both members of every (cos, sin) pair must be inside it.

    Returns
    -------
    (n, n) orthogonal matrix ``Rz`` with ``z_tel = Rz @ z_cam``; ``Rz.T`` maps back.

    Notes
    -----
    A camera-frame pupil point ``u_c`` is the telescope-frame point ``R(angle) u_c``, so
    ``W_cam(u_c) = W_tel(R u_c)``. For one pair ``a cos(m phi) + b sin(m phi)`` of the
    telescope frame that gives ``a_c = a cos(m angle) + b sin(m angle)``,
    ``b_c = -a sin(m angle) + b cos(m angle)``; the inverse is the block
    ``[[cos, -sin], [sin, cos]](m angle)`` applied to ``(a_c, b_c)``. ``m = 0`` terms are
    unchanged.
    """
    js = range(noll_min, noll_max + 1)
    n_terms = noll_max - noll_min + 1
    out = np.eye(n_terms)
    for j in js:
        n, m = noll_to_nm(j)
        if m <= 0:
            continue
        # the sine partner of cos term j has the same n, |m| and an adjacent Noll index
        partner = j + 1 if noll_to_nm(j + 1) == (n, -m) else j - 1
        if not noll_min <= partner <= noll_max:
            raise ValueError(f"Noll {j}'s sine partner {partner} is outside "
                             f"{noll_min}..{noll_max}")
        c, s = np.cos(m * angle_rad), np.sin(m * angle_rad)
        ic, is_ = j - noll_min, partner - noll_min
        out[ic, ic], out[ic, is_] = c, -s
        out[is_, ic], out[is_, is_] = s, c
    return out


def dof_rotation_matrix(angle_rad: float) -> np.ndarray:
    """The telescope-frame equivalent of a DoF vector applied to the rotated camera.

    Parameters
    ----------
    angle_rad : rotator angle [rad] (``batoid.RotZ`` argument).

    Returns
    -------
    (50, 50) orthogonal matrix ``M``: the telescope rotated by ``angle`` and perturbed by ``x``
    is optically the unrotated telescope perturbed by ``M @ x`` (then its detector turned by
    ``angle``). ``M`` is the identity except for the camera tilt (DoF 8, 9), which
    batoid_rubin applies as ``RotX(-rx) @ RotY(ry)`` about the rotated camera's axes: its
    rotation vector ``(-rx, ry)`` (batoid axes; the minus is the OCS x -> -x flip) turns by
    ``R(angle)``, so ``rx' = cos a rx + sin a ry`` and ``ry' = -sin a rx + cos a ry``.
    ``M.T`` maps a telescope-frame camera tilt back to the one to command.
    """
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    out = np.eye(N_DOF)
    i, k = CAMERA_FRAME_DOF
    out[i, i], out[i, k] = c, s
    out[k, i], out[k, k] = -s, c
    return out
