"""Geometric donuts of an ideal paraxial lens with an injected wavefront (paper §4.1).

A paraxial (thin, aberration-free) lens of focal length f and pupil radius R sends the ray
from reduced pupil point (x, y) straight to the focus; a wavefront W deflects it by its slope.
On a plane at distance l before (intra) or after (extra) focus the ray lands at

    intra: (x', y') = +l R / f (x, y) - (f - l) grad_U W,
    extra: (x', y') = -l R / f (x, y) - (f + l) grad_U W,

with ``grad_U = grad / R`` the slope per unit pupil length.  Photons are drawn uniformly over the
annular pupil, pushed through this map and binned into pixels: flux conservation (the
Jacobian), caustics and pixel sampling then come out of the counting, not from a formula.
This is the paper's paraxial unit test; batoid has no ideal thin lens, so this is written here.
The wavefront gradient comes from GalSim's Zernike polynomials, not from the estimator's code.
"""

from __future__ import annotations

import numpy as np
from galsim.zernike import Zernike

from cwfs_ros.sim.sampling import annulus_samples
from cwfs_ros.wfs.instrument import Instrument

__all__ = ["render_paraxial_pair"]


def render_paraxial_pair(inst: Instrument, zernikes_nm: dict[int, float] | np.ndarray, *,
                         defocus_mm: float | None = None, npix: int = 120,
                         n_photons: float = 1e6, rng: np.random.Generator | None = None,
                         poisson: bool = True, sampling: str = "random"
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Render (intra, extra) donuts ``[row=y, col=x]`` of a paraxial lens with wavefront W.

    Args:
        inst: geometry (focal length, aperture, obscuration, pixel size).
        zernikes_nm: annular Noll coefficients of W in nm, as {j: value} or an array whose
            index k holds Z_(k+1).
        defocus_mm: |detector offset|; the instrument's by default.
        npix: stamp side; the donut is centred on the stamp centre.
        n_photons: photons per image (each photon is one ray).
        rng: random generator.
        poisson: draw the number of photons from a Poisson distribution.
        sampling: ``"random"`` pupil points (photon shot noise), or ``"quasi"``: a
            scrambled Sobol sequence, with ``poisson=False`` an (almost) noise-free image
            (see :func:`cwfs_ros.sim.render.trace_pupil_rays`).
    """
    rng = np.random.default_rng() if rng is None else rng
    if isinstance(zernikes_nm, dict):
        coef = np.zeros(max(zernikes_nm) + 1)
        for j, v in zernikes_nm.items():
            coef[j] = v
    else:
        coef = np.concatenate([[0.0], np.asarray(zernikes_nm, float)])
    wf = Zernike(coef * 1e-9, R_outer=1.0, R_inner=inst.obscuration)  # metres of OPD
    gx, gy = wf.gradX, wf.gradY
    l_m = (defocus_mm or inst.defocal_offset_mm) * 1e-3
    f, big_r, pix = inst.focal_length_m, inst.pupil_radius_m, inst.pixel_size_um * 1e-6
    out = []
    for sign, dist in ((1.0, f - l_m), (-1.0, f + l_m)):
        n = rng.poisson(n_photons) if poisson else int(n_photons)
        r, t = annulus_samples(rng, n, inst.obscuration, sampling)
        x, y = r * np.cos(t), r * np.sin(t)
        xs = sign * l_m * big_r / f * x - dist * gx(x, y) / big_r
        ys = sign * l_m * big_r / f * y - dist * gy(x, y) / big_r
        col = xs / pix + npix / 2.0
        row = ys / pix + npix / 2.0
        img, _, _ = np.histogram2d(row, col, bins=npix, range=[[0, npix], [0, npix]])
        out.append(img)
    return out[0], out[1]
