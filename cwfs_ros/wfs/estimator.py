"""The curvature wavefront estimator: preprocessing, outer compensation loop, TIE solve.

This is the paper's Fig. 3 algorithm.  One call of :func:`estimate_wavefront` takes an
intra- and an extra-focal donut and returns the annular Zernikes Z4..Z22 of the wavefront
(nm of OPD) at the mid-point of the two stars' field positions.

Outer loop (paper §2.1): start from W = 0; at iteration k compensate both images with the
accumulated wavefront ``W_comp`` (:mod:`.compensation`), solve the TIE for the residual
``W_res`` (:mod:`.tie`), and feed back ``gain * W_res`` restricted to Noll indices up to the
compensation schedule's k-th entry.  The estimate after iteration k is ``W_comp + W_res``.
Stop early once the full jmax is compensated and the residual rms falls below a tolerance;
stop and keep the last good estimate if the compensation folds into caustic.

Split sensor and off-axis (§3.3-3.4): each image has its own mapping at its own star's field
angle, which removes distortion and that field's design aberrations; the vignetting masks of
the two images are combined into the common pupil mask; the design wavefront at the
mid-point field is added back so that the result is the total wavefront there.

Pupil registration (beyond the paper): the images are first aligned by flux centroid, whose
model depends on the vignetting model; every outer iteration then measures the shift of the
compensated pupils on the primary's outer rim (the stop, where the model is exact) away from
any vignetting edge, and moves both images to undo it.  A vignetting model a pixel off (the
FAM edge fields) otherwise shifts both pupils against the mapping, and the design wavefront,
sampled at shifted pupil points, reads as tens of nm of astigmatism and coma.

Input checks (:mod:`.checks`): each stamp is rejected if saturated (a configured level, or a
flat-topped plateau at its maximum), and the pair if the intra and extra images look
exchanged (off axis, from the vignetted footprints the geometry predicts for each side).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from functools import cached_property, lru_cache, partial
from typing import Any

import numpy as np
import yaml
from scipy import fft as sfft
from scipy.linalg import solve_triangular
from scipy.ndimage import distance_transform_edt, gaussian_filter, maximum_filter1d

from cwfs_ros.config import config_dir
from cwfs_ros.errors import ConfigError, ShapeMismatchError, StampTooSmallError
from cwfs_ros.layout import NOLL
from cwfs_ros.wfs.blur import blur_reference, check_seeing, image_blur_sigma_px
from cwfs_ros.wfs.checks import (
    CheckConfig,
    PairFootprints,
    SwapScore,
    check_not_swapped,
    check_orientation,
    pair_footprints,
    stamp_windows,
)
from cwfs_ros.wfs.compensation import Compensated, compensate
from cwfs_ros.wfs.donuts import PreparedDonut, prepare_donut
from cwfs_ros.wfs.instrument import Instrument, load_instrument
from cwfs_ros.wfs.mapping import (
    ImageMapping,
    design_zernikes_tiled,
    nominal_mapping,
    pupil_transmission,
    reset_field_tiles,
    tile_of,
    warm_field_tiles,
)
from cwfs_ros.wfs.tie import SOLVERS, IterativeFFT, LeastSquares, SeriesExpansion
from cwfs_ros.wfs.zernike import ZernikeBasis, gram_matrix, zernike_basis

__all__ = ["estimate_wavefront", "WavefrontResult", "AlgorithmConfig", "EstimateConfig",
           "load_algorithm", "load_checks", "PairGeometry", "pair_geometry", "warm_star_fields"]

NOLL_REPORTED = np.asarray(NOLL)  # Z4..Z22, the published product


@dataclass(frozen=True)
class AlgorithmConfig:
    """Parameters of the outer loop and solver (``config/algorithm.yaml``)."""

    solver: str
    outer_iterations: int
    feedback_gain: float
    compensation_sequence: tuple[int, ...]
    boundary_px: int
    oversample: int
    jmax: int
    tolerance_nm: float
    inner_iterations: int = 6
    edge_sigma_px: float = 1.0
    smooth_sigma_px: float = 1.0
    # Basis in which the outer loop truncates the feedback to the schedule's Noll index:
    # "zernike" (the paper) or "orthonormal" (the annular Zernikes Gram-Schmidt
    # orthonormalised on the common vignetted pupil, §3.3; see docs/accuracy.md).
    feedback_basis: str = "zernike"
    # Register the compensated pupils on the primary's outer rim at every outer iteration
    # (corrects centroid alignment biased by vignetting-model errors; docs/accuracy.md).
    register_rim: bool = True
    # Side (deg) of the field tiles over which the design wavefront is interpolated
    # (:func:`.mapping.design_zernikes_tiled`; ~0.1 nm from the direct trace); 0: direct.
    design_tile_deg: float = 0.0
    # Side (deg) of the field tiles over which the batoid mapping is interpolated
    # (:func:`.mapping._batoid_tiled`); 0: every star field traced directly.
    map_tile_deg: float = 0.0
    # Star pairs of one corner after the first start their outer loop from its departure
    # (estimate_wavefront(initial_nm=...), cwfs_ros.frames.selection.estimate_pairs).  Only
    # where the configured loop reaches its fixed point, which then does not depend on the
    # start: lsq does; exp and fft stop short of it on split pairs (docs/accuracy.md).
    warm_start: bool = False
    # Feedback gain of a warm-started loop (estimate_wavefront(initial_nm=...)): near its
    # fixed point the loop is linear and the lsq model's response matches the images'
    # (contraction 0.39 per iteration at gain 0.6), so the full step converges in ~4
    # iterations instead of ~8, to the same point within 0.02 nm (docs/accuracy.md, Frames).
    warm_start_gain: float = 0.6
    # Subtract the edge signal of the image blur (seeing, pixels, smoothing) from the
    # difference image, predicted from the compensated design donuts (:mod:`.blur`).
    blur_reference: bool = False

    def __post_init__(self) -> None:
        problems = []
        if self.solver not in SOLVERS:
            problems.append(f"solver must be one of {sorted(SOLVERS)}, got {self.solver!r}")
        if not isinstance(self.outer_iterations, int) or self.outer_iterations < 1:
            problems.append(f"outer_iterations must be an integer >= 1, got "
                            f"{self.outer_iterations!r}")
        if not (isinstance(self.feedback_gain, (int, float)) and 0 < self.feedback_gain <= 1):
            problems.append(f"feedback_gain must be in (0, 1], got {self.feedback_gain!r}")
        if not isinstance(self.jmax, int) or self.jmax < 22:
            problems.append(f"jmax must be an integer >= 22, got {self.jmax!r}")
        if not self.compensation_sequence or any(
            not isinstance(j, int) or j < 1 for j in self.compensation_sequence
        ):
            problems.append("compensation_sequence must be a list of Noll indices >= 1")
        if not isinstance(self.boundary_px, int) or self.boundary_px < 1:
            problems.append(f"boundary_px must be an integer >= 1, got {self.boundary_px!r}")
        if not isinstance(self.oversample, int) or not 1 <= self.oversample <= 8:
            problems.append(f"oversample must be an integer in 1..8, got {self.oversample!r}")
        if not (isinstance(self.tolerance_nm, (int, float)) and self.tolerance_nm >= 0):
            problems.append(f"tolerance_nm must be >= 0, got {self.tolerance_nm!r}")
        if not isinstance(self.inner_iterations, int) or self.inner_iterations < 1:
            problems.append(f"inner_iterations must be an integer >= 1, got "
                            f"{self.inner_iterations!r}")
        if not (isinstance(self.design_tile_deg, (int, float))
                and 0 <= self.design_tile_deg <= 1):
            problems.append(f"design_tile_deg must be in [0, 1], got {self.design_tile_deg!r}")
        if not (isinstance(self.map_tile_deg, (int, float)) and 0 <= self.map_tile_deg <= 1):
            problems.append(f"map_tile_deg must be in [0, 1], got {self.map_tile_deg!r}")
        if not (isinstance(self.warm_start_gain, (int, float))
                and 0 < self.warm_start_gain <= 1):
            problems.append(f"warm_start_gain must be in (0, 1], got {self.warm_start_gain!r}")
        if not isinstance(self.warm_start, bool):
            problems.append(f"warm_start must be true or false, got {self.warm_start!r}")
        if not isinstance(self.blur_reference, bool):
            problems.append(f"blur_reference must be true or false, got "
                            f"{self.blur_reference!r}")
        if self.feedback_basis not in ("zernike", "orthonormal"):
            problems.append(f"feedback_basis must be 'zernike' or 'orthonormal', got "
                            f"{self.feedback_basis!r}")
        if problems:
            raise ConfigError("algorithm: " + "; ".join(problems))

    def schedule(self) -> list[int]:
        """Highest compensated Noll index per outer iteration (last entry repeats)."""
        seq = list(self.compensation_sequence)
        seq += [seq[-1]] * max(0, self.outer_iterations - len(seq))
        return [min(j, self.jmax) for j in seq[: self.outer_iterations]]


@lru_cache(maxsize=4)
def _algorithm_yaml(path: str, mtime: float) -> dict[str, Any]:
    try:
        with open(path, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read algorithm file {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"algorithm file {path} must hold a mapping per solver")
    return data


def load_algorithm(solver: str = "exp", **overrides: Any) -> AlgorithmConfig:
    """The solver's parameters from ``config/algorithm.yaml``, with keyword overrides."""
    path = config_dir() / "algorithm.yaml"
    data = _algorithm_yaml(str(path), path.stat().st_mtime if path.exists() else 0.0)
    if solver not in SOLVERS:
        raise ConfigError(f"unknown solver {solver!r}: choose one of {sorted(SOLVERS)}")
    params = dict(data.get(solver) or {})
    params.update({k: v for k, v in overrides.items() if v is not None})
    if "compensation_sequence" in params:
        params["compensation_sequence"] = tuple(params["compensation_sequence"])
    try:
        return AlgorithmConfig(solver=solver, **params)
    except TypeError as exc:
        raise ConfigError(f"algorithm parameters for {solver!r}: {exc}") from exc


def load_checks(**overrides: Any) -> CheckConfig:
    """The input checks' parameters (``input_checks`` in ``config/algorithm.yaml``)."""
    path = config_dir() / "algorithm.yaml"
    data = _algorithm_yaml(str(path), path.stat().st_mtime if path.exists() else 0.0)
    return CheckConfig.from_mapping(data.get("input_checks"), **overrides)


_CHECK_KEYS = frozenset(f.name for f in fields(CheckConfig))


# -- geometry: everything that depends only on the instrument, fields and algorithm ---------

@dataclass(frozen=True)
class PairGeometry:
    """Cached pupil sampling, masks, mappings, Zernike basis and solver for one pair geometry.

    Attributes:
        shape: (n, n) pupil grid; ``spacing`` in reduced pupil units per sample.
        region: flat indices of the computation points (pupil mask dilated by the boundary).
        x, y: reduced pupil coordinates of the computation points.
        mask_intra, mask_extra: transmitted (unvignetted) pupil of each image, on the points.
        mask_common: logical AND of the two (paper §3.4).
        weight: 1 where the signal is used, 0 where only one of the two images is transmitted.
        mapping_intra, mapping_extra: unperturbed mappings at each star's field.
        kappa: ``kappa_intra - kappa_extra`` (see :mod:`.tie`), per nm of Laplacian.
        intrinsic_nm: design wavefront Z1..Z_jmax (nm) at the mid-point field.
        gram_common: Gram matrix of Z1..Z_jmax over the common pupil (§3.3: the identity
            on a full annulus, not on a vignetted pupil).
        feedback_l: Cholesky factor L of ``gram_common`` (``Z = L U`` with U orthonormal on
            the common pupil) when the feedback is truncated in that basis, else None.
        rim_index, rim_pinv: computation points of the pupil-registration band on the
            primary's outer rim where neither image is vignetted, and the (3, n) least-squares
            operator giving (level, level * shift_x, level * shift_y) of the mean
            compensated image there (see :func:`_rim_registration`); None if too few.
        jac_mean_intra, jac_mean_extra: mean mapping Jacobian (px per pupil unit), which
            turns a pupil shift into the image shift that undoes it.
        footprints: predicted image-plane footprints of both images for the swapped-pair
            check (:func:`.checks.pair_footprints`), built on first use (~3 ms): a corner
            whose frames are confirmed the right way round skips the check for its further
            pairs (:func:`cwfs_ros.frames.selection.estimate_pairs`).
    """

    shape: tuple[int, int]
    spacing: float
    region: np.ndarray
    x: np.ndarray
    y: np.ndarray
    mask_intra: np.ndarray
    mask_extra: np.ndarray
    mask_common: np.ndarray
    weight: np.ndarray
    mapping_intra: ImageMapping
    mapping_extra: ImageMapping
    basis: ZernikeBasis
    solver: SeriesExpansion | IterativeFFT | LeastSquares
    kappa: float
    intrinsic_nm: np.ndarray
    field_mid_deg: tuple[float, float]
    outer_radius_px: float
    centroid_model_intra: np.ndarray
    centroid_model_extra: np.ndarray
    mean_gradient_intra: np.ndarray
    mean_gradient_extra: np.ndarray
    build_time_s: float = 0.0
    feedback_l: np.ndarray | None = None
    rim_index: np.ndarray | None = None
    rim_pinv: np.ndarray | None = None
    jac_mean_intra: np.ndarray | None = None
    jac_mean_extra: np.ndarray | None = None
    footprint_inputs: tuple | None = field(default=None, repr=False)
    obscuration: float = 0.0
    # Each side's f(x, y) -> transmitted, for pupil points off the grid (mapping
    # .pupil_transmission at the star's field): the blur reference's exact vignetting edges.
    transmissions: tuple = field(default=(None, None), repr=False, compare=False)
    # blur_reference() results by (blur, stamp shape): each pair's geometry meets one seeing
    # and one stamp size per visit.
    _blur_refs: dict = field(default_factory=dict, repr=False, compare=False)

    @cached_property
    def gram_common(self) -> np.ndarray:
        """Gram matrix of Z1..Z_jmax over the common pupil, built on first use (~1 ms; only
        the orthonormal feedback and the Gram report read it)."""
        gram = gram_matrix(self.basis, self.mask_common, j_min=1, j_max=self.basis.jmax)
        gram.setflags(write=False)
        return gram

    @cached_property
    def footprints(self) -> PairFootprints | None:
        return None if self.footprint_inputs is None else _footprints(*self.footprint_inputs)

    def blur_reference(self, blur_px: float, stamp_shape: tuple[int, int]) -> np.ndarray:
        """The edge signal of an image blur of ``blur_px`` (sigma beyond the pixels) in the
        weighted difference image, for stamps of ``stamp_shape`` (:func:`.blur.blur_reference`;
        cached; ~25 ms to build, most of it the two design donuts; bench_blur_reference.py)."""
        key = (round(float(blur_px), 4), tuple(stamp_shape))
        ref = self._blur_refs.get(key)
        if ref is None:
            if len(self._blur_refs) >= 4:
                self._blur_refs.clear()
            ref = blur_reference((self.mapping_intra, self.mapping_extra), self.x, self.y,
                                 self.spacing, self.obscuration, self.weight, key[1], key[0],
                                 self.transmissions, (self.shape, self.region))
            ref.setflags(write=False)
            self._blur_refs[key] = ref
        return ref

    def pupil_image(self, values: np.ndarray, fill: float = np.nan) -> np.ndarray:
        """Scatter values on the computation points into an (n, n) image for display."""
        out = np.full(self.shape[0] * self.shape[1], fill)
        out[self.region] = values
        return out.reshape(self.shape)


def _disk(radius: int) -> np.ndarray:
    """Boolean disk structuring element of the given radius in grid samples."""
    yy, xx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    return xx * xx + yy * yy <= radius * radius


@lru_cache(maxsize=16)
def _disk_rectangles(radius: int) -> tuple[tuple[int, int], ...]:
    """Half-widths (x, y) of the rectangles whose union is ``_disk(radius)``: one per step
    of the disk's staircase edge (radius 4: 4 rectangles)."""
    w = [int(np.floor(np.sqrt(radius * radius - d * d) + 1e-9)) for d in range(radius + 1)]
    return tuple((w[d], d) for d in range(radius + 1) if d == radius or w[d] > w[d + 1])


# Up to this radius the rectangle decomposition beats the distance transform (radius 4:
# 1.1 against 2.8 ms on a 150 x 150 pupil grid; radius 12: 3.4 against 2.8 ms).
_DILATE_RECT_MAX = 6
# :func:`_dilate` stamps the disk at the mask's edge pixels while that writes fewer than this
# many pixels per pixel of the mask's box: a stamped write costs about a tenth of a box
# pixel's passes (a 150 x 150 LSST pupil union at radius 4: 0.10 against 0.32 ms; the rim's
# vignetted lunes at radius 12, 0.15 against 0.21 ms for the transform).
_STAMPS_PER_BOX_PIXEL = 12


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """``binary_dilation(mask, structure=_disk(radius))``, computed fast, on the box of the
    mask's True pixels widened by the radius (nothing beyond it can change); ``radius`` in
    whole grid samples.

    Where the mask's edge is short (pupils, their rims, thin slivers): the disk stamped at
    each edge pixel.  The nearest mask pixel to a pixel outside the mask has a 4-neighbour
    outside it (one step towards that pixel is nearer still), so the edge pixels' disks
    hold every pixel the dilation adds.  Otherwise, small radii: the union of the dilations
    by the disk's rectangles (:func:`_disk_rectangles`), each separable into two running
    maxima; larger ones: a Euclidean distance transform (a pixel is within the disk of some
    True pixel iff its distance to the nearest one is <= radius; the squared distances are
    integers, so the float comparison is exact), whose cost does not grow with the radius.
    All give the same set (test_geometry_speed).
    """
    r = int(radius)
    out = np.zeros(mask.shape, bool)
    rows = np.flatnonzero(mask.any(axis=1))
    if not rows.size:
        return out
    # Beyond the box every pixel is False, as the filters' constant padding and the
    # transform assume, so the box gives the same set.
    cols = np.flatnonzero(mask.any(axis=0))
    box = (slice(max(int(rows[0]) - r, 0), int(rows[-1]) + r + 1),
           slice(max(int(cols[0]) - r, 0), int(cols[-1]) + r + 1))
    m = mask[box]
    h, w = m.shape
    edge = np.flatnonzero(m & ~_interior(m))
    offsets = _disk_offsets(r, w + 2 * r)
    if edge.size * offsets.size < _STAMPS_PER_BOX_PIXEL * m.size:
        # Stamped on the box padded by the radius, whose flat offsets need no bounds.
        padded = np.zeros((h + 2 * r) * (w + 2 * r), bool)
        at = (edge // w + r) * (w + 2 * r) + edge % w + r
        padded[(at[:, None] + offsets).ravel()] = True
        out[box] = padded.reshape(h + 2 * r, w + 2 * r)[r:r + h, r:r + w] | m
        return out
    out[box] = _dilate_box(m, r)
    return out


def _interior(m: np.ndarray) -> np.ndarray:
    """The pixels of ``m`` whose four neighbours are all in it (beyond the array's edge
    counts as in it: the dilation's pixels all lie inside).  ``binary_erosion(m,
    border_value=1)`` gives the same set in ten times the time (144 against 15 us on a
    150 x 150 pupil), which would undo most of what stamping saves."""
    inner = m.copy()
    inner[1:] &= m[:-1]
    inner[:-1] &= m[1:]
    inner[:, 1:] &= m[:, :-1]
    inner[:, :-1] &= m[:, 1:]
    return inner


@lru_cache(maxsize=64)
def _disk_offsets(radius: int, width: int) -> np.ndarray:
    """Flat offsets, on rows of ``width``, of the points of :func:`_disk` ``(radius)``."""
    dy, dx = np.nonzero(_disk(radius))
    flat = (dy - radius) * width + (dx - radius)
    flat.setflags(write=False)
    return flat


def _dilate_box(mask: np.ndarray, radius: int) -> np.ndarray:
    """:func:`_dilate` of a mask that has True pixels, on all of it."""
    if radius > _DILATE_RECT_MAX:
        return distance_transform_edt(~mask) <= radius
    m = mask.astype(np.uint8)
    out = np.zeros(mask.shape, bool)
    for a, b in _disk_rectangles(radius):
        t = maximum_filter1d(m, 2 * a + 1, axis=1, mode="constant") if a else m
        t = maximum_filter1d(t, 2 * b + 1, axis=0, mode="constant") if b else t
        out |= t.astype(bool)
    return out


def _kappa(m: ImageMapping, mask: np.ndarray) -> float:
    """Image contrast per unit Laplacian, ``C tr(A^-1) / 2`` averaged over the pupil."""
    tr_inv = (m.jxx + m.jyy) / m.det
    return float(m.c_px_per_nm * np.mean(tr_inv[mask]) / 2.0)


def _rim_registration(shape: tuple[int, int], spacing: float, region: np.ndarray,
                      r: np.ndarray, annulus: np.ndarray, mask_in: np.ndarray,
                      mask_ex: np.ndarray, r_d: float, algo: AlgorithmConfig
                      ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Points and operator registering the compensated images on the primary's outer rim
    (``r``: the computation points' pupil radii, in pupil radii).

    The images are aligned by their flux centroids, whose model depends on the vignetting
    model: where the real vignetting edges differ from the model's by a pixel (the FAM edge
    fields, docs/design.md), the centroids put both compensated pupils ~1.5 px off the mapping, and
    the design wavefront, sampled at shifted pupil points, reads as tens of nm of
    astigmatism and coma.  The primary's outer edge is the pupil stop, known exactly; on
    the arcs where no vignetting edge is near, the mean of the two compensated images,
    in which the wavefront's edge signals cancel (they move the intra and extra edges
    oppositely, §2.1), is fitted as ``L * M_b(p - s)`` (``M_b``: the mask blurred like the
    images), linearised in the pupil shift s.
    """
    n = shape[0]
    band = 4.0 + 2.0 * algo.smooth_sigma_px  # px either side of the rim
    reach = int(np.ceil(2 * band * algo.oversample))  # grid samples
    rim_gap = np.abs(r - 1.0)
    untrusted = np.zeros(n * n, bool)
    # Points farther than the reach from the rim band cannot mark a band point (the triangle
    # inequality on the radii): left out, the dilation's box shrinks to the vignetted lunes
    # at the rim, and the central obscuration's edges drop out.
    untrusted[region] = (((annulus ^ mask_in) | (annulus ^ mask_ex))
                         & (rim_gap <= band / r_d + (reach + 1) * spacing))
    untrusted = _dilate(untrusted.reshape(n, n), reach)
    sel = (rim_gap <= band / r_d) & ~untrusted.ravel()[region]
    if sel.sum() < 200:
        return None, None
    sigma = np.hypot(algo.smooth_sigma_px, np.sqrt(1.0 / 12.0)) * algo.oversample
    grid = np.zeros(n * n)
    grid[region] = 0.5 * (mask_in.astype(float) + mask_ex.astype(float))
    mb = gaussian_filter(grid.reshape(n, n), sigma).ravel()
    idx = region[sel]
    design = np.stack([mb[idx], *(-g for g in _central_gradient(mb, n, idx, spacing))],
                      axis=1)
    normal = design.T @ design
    if np.linalg.cond(normal) > 1e8:
        return None, None
    # The 3 x 3 inverse times the design: np.linalg.solve with the design's thousands of
    # columns as right-hand sides costs ten times more, for the same operator.
    return np.flatnonzero(sel), (np.linalg.inv(normal) @ design.T).astype(np.float32)


def _central_gradient(f: np.ndarray, n: int, idx: np.ndarray, spacing: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(d/dx, d/dy) of the flat (n, n) grid ``f`` at its points ``idx``, as
    ``np.gradient(f.reshape(n, n), spacing)`` gives them there, without the whole grid's."""
    rows, cols = np.divmod(idx, n)
    if rows.min() < 1 or cols.min() < 1 or rows.max() > n - 2 or cols.max() > n - 2:
        gy, gx = np.gradient(f.reshape(n, n), spacing)  # one-sided at the grid's edge
        return gx.ravel()[idx], gy.ravel()[idx]
    h2 = 2.0 * spacing
    return (f[idx + 1] - f[idx - 1]) / h2, (f[idx + n] - f[idx - n]) / h2


def _footprints(m_in: ImageMapping, m_ex: ImageMapping, grid_in: np.ndarray,
                grid_ex: np.ndarray, cand: np.ndarray, n: int,
                outer_radius_px: float) -> PairFootprints:
    """Footprints of the swapped-pair check (:func:`.checks.pair_footprints`).

    ``m_in``/``m_ex`` are mapped at the candidate points ``cand`` (the whole annulus plus
    boundary); ``grid_in``/``grid_ex`` the transmitted masks on the (n, n) pupil grid, which
    is symmetric about the pupil centre, so reversing both axes turns a mask by 180 degrees.
    """
    pts = []
    for m, grid in ((m_in, grid_in), (m_ex, grid_ex)):
        turned = grid.reshape(n, n)[::-1, ::-1].ravel()[cand]
        pts.append(((m.x_px[m.transmitted], m.y_px[m.transmitted]),
                    (m.x_px[turned], m.y_px[turned])))
    return pair_footprints((pts[0], pts[1]), outer_radius_px)


def _mean_jacobian(m: ImageMapping) -> np.ndarray:
    t = m.transmitted_index
    return np.array([[m.jxx.take(t).mean(), m.jxy.take(t).mean()],
                     [m.jyx.take(t).mean(), m.jyy.take(t).mean()]], dtype=float)


@lru_cache(maxsize=4)
def _pupil_grid(n: int, spacing: float, extent: float, obscuration: float, jmax: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, ZernikeBasis]:
    """Candidate points of the (n, n) pupil grid, their coordinates and Zernike basis.

    Field-independent: every pair of one instrument and defocus shares the grid, and a new
    field only selects its computation region from it (:meth:`ZernikeBasis.subset`), which
    saves the basis and its derivatives per star pair (~4 ms, docs/performance.md).
    """
    ax = (np.arange(n) - (n - 1) / 2.0) * spacing
    gx, gy = np.meshgrid(ax, ax)
    r = np.hypot(gx, gy).ravel()
    cand = np.flatnonzero((r <= extent) & (r >= obscuration - (extent - 1.0)))
    x, y = gx.ravel()[cand], gy.ravel()[cand]
    basis = zernike_basis(x, y, jmax=jmax, eps=obscuration, dtype=np.float32)
    _ = basis.dx, basis.dy  # built once here, indexed per pair
    for a in (cand, x, y):
        a.setflags(write=False)
    return cand, x, y, basis


@lru_cache(maxsize=4)
def _candidate_radii(n: int, spacing: float, extent: float, obscuration: float, jmax: int
                     ) -> np.ndarray:
    """Pupil radius of each of :func:`_pupil_grid`'s candidate points."""
    _, x, y, _ = _pupil_grid(n, spacing, extent, obscuration, jmax)
    r = np.hypot(x, y)
    r.setflags(write=False)
    return r


@lru_cache(maxsize=4)
def _candidate_positions(n: int, spacing: float, extent: float, obscuration: float,
                         jmax: int) -> np.ndarray:
    """Position in :func:`_pupil_grid`'s candidate points of each (n, n) grid sample, -1
    off them: a field's computation region is read from it rather than searched for."""
    cand = _pupil_grid(n, spacing, extent, obscuration, jmax)[0]
    lut = np.full(n * n, -1, dtype=np.intp)
    lut[cand] = np.arange(cand.size)
    lut.setflags(write=False)
    return lut


@lru_cache(maxsize=32)
def pair_geometry(inst: Instrument, band: str, wavelength_nm: float,
                  field_intra_deg: tuple[float, float], field_extra_deg: tuple[float, float],
                  defocus_mm: float, algo: AlgorithmConfig) -> PairGeometry:
    """Build (and cache) the geometry of an intra/extra pair.  Depends on no image data.

    The pupil grid (:func:`_grid_side`), each image's mapping at its own star's field
    (§3.2-3.3), the computation region and the common-pupil signal weight (§3.4), the
    solver, the design wavefront at the mid-point field (§3.4) and the alignment models.
    """
    t0 = time.perf_counter()
    r_d = inst.donut_radius_px(defocus_mm)
    spacing, extent, n = _grid_side(r_d, algo)
    cand, x, y, grid_basis = _pupil_grid(n, spacing, extent, inst.obscuration, algo.jmax)
    kw = dict(defocus_mm=defocus_mm, band=band, wavelength_nm=wavelength_nm,
              tile_deg=algo.map_tile_deg)
    full_in = nominal_mapping(inst, "intra", x, y, field_deg=field_intra_deg, **kw)
    full_ex = nominal_mapping(inst, "extra", x, y, field_deg=field_extra_deg, **kw)
    grid_in, grid_ex = (_on_grid(n, cand, m.transmitted) for m in (full_in, full_ex))
    if not (grid_in & grid_ex).any():
        raise ConfigError("intra and extra pupils do not overlap: check the field angles")
    # Computation region: the union of the pupils dilated by the boundary thickness.
    region2d = _dilate((grid_in | grid_ex).reshape(n, n), algo.boundary_px * algo.oversample)
    cand_pos = _candidate_positions(n, spacing, extent, inst.obscuration, algo.jmax)
    region = np.flatnonzero(region2d.ravel() & (cand_pos >= 0))
    pos = cand_pos[region]
    m_in, m_ex = _on_region(full_in, pos), _on_region(full_ex, pos)
    x, y = x[pos], y[pos]
    mask_in, mask_ex = m_in.transmitted, m_ex.transmitted
    common = mask_in & mask_ex
    weight = _signal_weight(n, region, mask_in, mask_ex, algo)
    basis = grid_basis.subset(pos)
    kappa = _kappa(m_in, common) - _kappa(m_ex, common)
    solver = _make_solver(algo, (n, n), spacing, region, basis, common, (m_in, m_ex), kappa,
                          weight)
    mid = (0.5 * (field_intra_deg[0] + field_extra_deg[0]),
           0.5 * (field_intra_deg[1] + field_extra_deg[1]))
    intrinsic = design_zernikes_tiled(inst, band, wavelength_nm, mid, algo.jmax,
                                      algo.design_tile_deg)
    (centroid_in, outer_in), (centroid_ex, outer_ex) = (_pupil_extent(m) for m in (m_in, m_ex))
    outer = max(outer_in, outer_ex)
    feedback_l = (np.linalg.cholesky(gram_matrix(basis, common, j_min=1, j_max=basis.jmax))
                  if algo.feedback_basis == "orthonormal" else None)
    rim_index, rim_pinv = (None, None)
    if algo.register_rim:
        r_pupil = _candidate_radii(n, spacing, extent, inst.obscuration, algo.jmax)[pos]
        annulus = (r_pupil <= 1.0) & (r_pupil >= inst.obscuration)
        rim_index, rim_pinv = _rim_registration((n, n), spacing, region, r_pupil, annulus,
                                                mask_in, mask_ex, r_d * algo.oversample,
                                                algo)
    for arr in (x, y, mask_in, mask_ex, common, weight, region):
        arr.setflags(write=False)
    transmissions = tuple(partial(pupil_transmission, inst, side, field_deg=f, **kw)
                          for side, f in (("intra", field_intra_deg), ("extra", field_extra_deg)))
    return PairGeometry((n, n), spacing, region, x, y, mask_in, mask_ex, common, weight,
                        m_in, m_ex, basis, solver, kappa, intrinsic, mid, outer,
                        centroid_in, centroid_ex,
                        _mean_gradient(basis, mask_in), _mean_gradient(basis, mask_ex),
                        time.perf_counter() - t0, feedback_l,
                        rim_index, rim_pinv, _mean_jacobian(m_in), _mean_jacobian(m_ex),
                        # The swapped-pair footprints are built on first use.
                        (full_in, full_ex, grid_in, grid_ex, cand, n, outer),
                        float(inst.obscuration), transmissions)


def _grid_side(r_d: float, algo: AlgorithmConfig) -> tuple[float, float, int]:
    """(spacing, extent, n) of the square pupil grid for a donut of radius ``r_d`` px.

    ``oversample`` grid samples per image pixel (§2.1's compensation oversampling).  The
    extent is generous: the fast beam enlarges the donut by ~4 % (§3.2), and the boundary
    adds more.  The side is transform-friendly, as the fft solver's cost depends on it.
    """
    spacing = 1.0 / (r_d * algo.oversample)
    extent = 1.08 + (algo.boundary_px + 3) / r_d
    n = sfft.next_fast_len(2 * int(np.ceil(extent / spacing)) + 1, real=True)
    return spacing, extent, n


def _on_grid(n: int, cand: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The candidate points' boolean ``values`` on the flat (n, n) pupil grid (False off
    them)."""
    grid = np.zeros(n * n, bool)
    grid[cand] = values
    return grid


def _on_region(m: ImageMapping, pos: np.ndarray) -> ImageMapping:
    """The mapping at the computation points ``pos`` (indices into the candidate points),
    float32: that halves the memory traffic of the per-iteration compensation, and positions
    keep ~1e-5 px precision on a 200 px stamp."""
    f32 = [np.ascontiguousarray(a[pos], dtype=np.float32)
           for a in (m.x_px, m.y_px, m.jxx, m.jxy, m.jyx, m.jyy)]
    return ImageMapping(m.side, *f32, m.transmitted[pos], m.c_px_per_nm, m.fit_rms_px)


def _signal_weight(n: int, region: np.ndarray, mask_in: np.ndarray, mask_ex: np.ndarray,
                   algo: AlgorithmConfig) -> np.ndarray:
    """1 where the difference image is used, 0 where only one image is transmitted and over
    a guard band around those places (float32, on the computation points).

    The blurred edge of the image that stops there reaches a couple of pixels into the
    common pupil, where the other image is still bright: paper §3.4's common mask, made
    robust to edge blur.  Edges the two pupils share keep their signal.
    """
    only_one = np.zeros(n * n, bool)
    only_one[region] = mask_in ^ mask_ex
    guard = int(np.ceil((2.0 + 2.0 * algo.smooth_sigma_px) * algo.oversample))
    near = _dilate(only_one.reshape(n, n), guard)
    return np.where(near.ravel()[region], 0.0, 1.0).astype(np.float32)


def _make_solver(algo: AlgorithmConfig, shape: tuple[int, int], spacing: float,
                 region: np.ndarray, basis: ZernikeBasis, common: np.ndarray,
                 mappings: tuple[ImageMapping, ImageMapping], kappa: float,
                 weight: np.ndarray) -> SeriesExpansion | IterativeFFT | LeastSquares:
    """The configured TIE solver (:mod:`.tie`): the paper's series expansion (§2.2) or
    iterative FFT (§2.1), or the least-squares fit on the annular basis."""
    if algo.solver == "exp":
        return SeriesExpansion(basis, common)
    if algo.solver == "fft":
        return IterativeFFT(shape, spacing, region, basis, common, algo.inner_iterations)
    return LeastSquares(shape, spacing, region, basis, common,
                        algo.edge_sigma_px * algo.oversample, mappings=mappings,
                        kappa=kappa, weight=weight)


def _pupil_extent(m: ImageMapping) -> tuple[np.ndarray, float]:
    """The flux centroid (x, y) px of the illuminated pupil under the mapping (W = 0), and
    the radius around it that holds the whole image (off axis the donut is neither centred
    on the chief ray nor round; a pair takes the larger of its two images')."""
    t = m.transmitted_index
    x, y = m.x_px.take(t), m.y_px.take(t)
    cx, cy = x.mean(), y.mean()
    return np.array([float(cx), float(cy)]), float(np.hypot(x - cx, y - cy).max())


def _mean_gradient(basis: ZernikeBasis, mask: np.ndarray) -> np.ndarray:
    """(2, jmax): mean over the pupil of dZ_j/dx and dZ_j/dy, which moves the centroid."""
    w = mask.astype(np.float32) / max(int(mask.sum()), 1)
    return np.stack([basis.dx @ w, basis.dy @ w]).astype(float)


# -- result -------------------------------------------------------------------------------

@dataclass
class WavefrontResult:
    """Outcome of one wavefront estimate.

    Attributes:
        zernikes_nm: Z4..Z22 (19 values) of the total wavefront at ``field_deg``, nm OPD.
        zernikes_all_nm: Z1..Z_jmax (index j-1), nm; Z1-Z3 are not measurable (set to 0).
        intrinsic_nm: design wavefront Z4..Z22 at ``field_deg`` that was added back (zero
            for non-ray-traced instruments); ``zernikes_nm - intrinsic_nm`` is the departure
            from design.
        noll: the Noll indices of ``zernikes_nm`` (4..22).
        caustic: the compensation folded into caustic; the estimate is the last good one.
        converged: the iteration settled: the last update (rms of the residual over
            Z4..Z_jmax) fell below the solver's ``tolerance_nm`` before the iteration limit.
            It says the outer loop stopped moving, not that the estimate is accurate:
            False only means the limit of iterations was reached first (read
            ``residual_rms_nm[-1]`` for the size of the last update).
        iterations: outer iterations run.
        history_nm: estimate Z1..Z_jmax after each outer iteration, shape (iterations, jmax).
        residual_rms_nm: rms of each iteration's residual over Z4..Z_jmax.
        field_deg: field of the result (mid-point of the two stars).
        wall_time_s: wall time of this call; ``geometry_time_s`` the part spent building the
            (cached) geometry, 0 when it was cached.
        masks: pupil masks used (2-D images on the pupil grid): intra, extra, common, region.
        compensated: final compensated intra and extra images on the pupil grid.
        inputs: preprocessing measurements of each donut.
        swap_check: outcome of the swapped-pair check: ``"confirmed"`` (the images are the
            right way round beyond doubt: preference above ``swap_threshold`` at
            ``swap_min_significance``), ``"inconclusive"`` (it ran and could not tell) or
            ``"off"`` (disabled, or no vignetting to tell by).  An exchanged pair raises.
    """

    zernikes_nm: np.ndarray
    zernikes_all_nm: np.ndarray
    intrinsic_nm: np.ndarray
    caustic: bool
    converged: bool
    iterations: int
    history_nm: np.ndarray
    residual_rms_nm: np.ndarray
    field_deg: tuple[float, float]
    wall_time_s: float
    geometry_time_s: float
    solver: str
    instrument: str
    band: str
    wavelength_nm: float
    masks: dict[str, np.ndarray] = field(repr=False)
    compensated: dict[str, np.ndarray] = field(repr=False)
    inputs: dict[str, PreparedDonut] = field(repr=False)
    noll: np.ndarray = field(default_factory=lambda: NOLL_REPORTED.copy())
    swap_check: str = "off"
    # Z1..Z_jmax (nm) of the departure from design (``zernikes_all_nm`` before the design
    # wavefront is added back; Z1-Z3 zero): what ``initial_nm`` of another pair takes.
    departure_all_nm: np.ndarray = field(default_factory=lambda: np.zeros(0), repr=False)

    def __repr__(self) -> str:
        # One line; the arrays are in the attributes (the default dataclass repr would be
        # ~6000 characters).
        dep = self.zernikes_nm - self.intrinsic_nm
        flags = [n for n, on in (("caustic", self.caustic), ("not settled", not self.converged))
                 if on]
        return (f"<WavefrontResult {self.instrument} {self.band} {self.wavelength_nm:g} nm, "
                f"{self.solver}, field ({self.field_deg[0]:.4f}, {self.field_deg[1]:.4f}) deg:"
                f" Z4..Z22 {np.sqrt(np.sum(self.zernikes_nm ** 2)):.1f} nm "
                f"(departure from design {np.sqrt(np.sum(dep ** 2)):.1f} nm, Z4 "
                f"{self.zernikes_nm[0]:.1f} nm), {self.iterations} iterations, swap_check "
                f"{self.swap_check}{''.join(', ' + f for f in flags)}>")

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly summary."""
        return {
            "noll": self.noll.tolist(),
            "zernikes_nm": [round(float(v), 4) for v in self.zernikes_nm],
            "intrinsic_nm": [round(float(v), 4) for v in self.intrinsic_nm],
            "caustic": bool(self.caustic),
            "converged": bool(self.converged),  # settled: last update below tolerance_nm
            "iterations": int(self.iterations),
            "swap_check": self.swap_check,
            "field_deg": [float(v) for v in self.field_deg],
            "solver": self.solver,
            "instrument": self.instrument,
            "band": self.band,
            "wavelength_nm": self.wavelength_nm,
            "wall_time_s": round(self.wall_time_s, 6),
        }


def warm_star_fields(inst: Instrument, band: str, wavelength_nm: float, algo: AlgorithmConfig,
                     side_fields: dict[str, Sequence[tuple[float, float]]],
                     mid_fields: Sequence[tuple[float, float]]) -> int:
    """Build what :func:`pair_geometry` reads from the field tiles for stars anywhere among
    ``side_fields`` (deg, per side) and pair mid-points among ``mid_fields``: the map and
    pupil tiles of each side and the design tiles, on the pupil grid pair_geometry uses.
    From then on those tiles serve every star field in them (:func:`.mapping.warm_field_tiles`).
    Returns the number of tiles built."""
    defocus_mm = inst.defocal_offset_mm
    spacing, extent, n = _grid_side(inst.donut_radius_px(defocus_mm), algo)
    _, x, y, _ = _pupil_grid(n, spacing, extent, inst.obscuration, algo.jmax)
    side_tiles = {side: [tile_of(f, algo.map_tile_deg) for f in fields]
                  for side, fields in side_fields.items()} if algo.map_tile_deg > 0 else {}
    mid_tiles = ([tile_of(f, algo.design_tile_deg) for f in mid_fields]
                 if algo.design_tile_deg > 0 else [])
    return warm_field_tiles(inst, x, y, side_tiles=side_tiles, mid_tiles=mid_tiles,
                            defocus_mm=defocus_mm, band=band, wavelength_nm=wavelength_nm,
                            tile_deg=algo.map_tile_deg, design_tile_deg=algo.design_tile_deg,
                            jmax=algo.jmax)


def reset_caches() -> None:
    """Drop the pair geometries and the field tiles (:func:`.mapping.reset_field_tiles`):
    the state of a freshly started worker process."""
    pair_geometry.cache_clear()
    reset_field_tiles()


def _field(value: Any, name: str) -> tuple[float, float]:
    try:
        fx, fy = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be two numbers (x, y) in degrees, got {value!r}") from None
    if not (np.isfinite(fx) and np.isfinite(fy)):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    return fx, fy  # within the instrument's field of view: Instrument.check_field


def estimate_wavefront(intra: np.ndarray, extra: np.ndarray, *,
                       field_intra_deg: tuple[float, float],
                       field_extra_deg: tuple[float, float],
                       instrument: str | Instrument = "lsst", band: str = "r",
                       wavelength_nm: float | None = None,
                       defocal_offset_mm: float | None = None, solver: str = "lsq",
                       saturation_level: float | None = None,
                       initial_nm: np.ndarray | None = None,
                       seeing_fwhm_arcsec: float = 0.0,
                       **algorithm: Any) -> WavefrontResult:
    """Estimate the wavefront from an intra/extra-focal donut pair (paper Fig. 3).

    The steps are those of the paper's block diagram: check the inputs
    (:meth:`EstimateConfig.from_options`), prepare the two donuts (:func:`_prepare_donuts`,
    :func:`_loop_inputs`), run the outer loop of compensation, TIE solve and update
    (:func:`_outer_loop`, §2.1), and report the total wavefront at the mid-point field
    (:func:`_result`, §3.4).

    Args:
        intra: image at negative detector offset, ``[row=y, col=x]`` in the focal-plane frame
            of the field angles (as batoid renders it).
        extra: image at positive detector offset, same frame (not rotated).
        field_intra_deg, field_extra_deg: field angles (x, y) of the two stars in degrees.
        instrument: name of a ``config/instruments`` YAML, a path to one, or an Instrument.
        band: optical band of the model (u, g, r, i, z, y); selects the batoid optic.
        wavelength_nm: wavelength; defaults to the band's effective wavelength.
        defocal_offset_mm: |detector offset|; defaults to the instrument's.
        solver: ``"lsq"`` (least squares, the default: the smallest error in every measured
            case, docs/accuracy.md), or the paper's ``"exp"`` (series expansion) and
            ``"fft"`` (iterative FFT), kept to reproduce its figures.
        saturation_level: pixel value (input units) at which the detector saturates;
            defaults to the instrument's ``saturation_level`` (None: unknown, and only the
            plateau test of :mod:`.checks` detects saturation).
        initial_nm: warm start: a departure from design (Noll Z1.., nm; Z1-Z3 ignored), e.g.
            another star pair's estimate on the same sensor.  The outer loop then starts
            compensated by it, at the full jmax from the first iteration (the schedule's
            ramp-up protects a start from zero against caustics) with the configured
            ``warm_start_gain``, and stops on convergence as usual.  Converged, the result
            does not depend on the start: the loop's fixed point is where the compensated
            images agree (docs/accuracy.md, Frames).
        seeing_fwhm_arcsec: atmospheric seeing (FWHM, arcsec) of the images, e.g. from the
            observatory's seeing monitor.  Where the solver's ``blur_reference`` is on
            (exp, lsq), the edge signal of the images' blur (the seeing, the pixels and the
            smoothing) is predicted and taken out of the difference image (:mod:`.blur`;
            docs/accuracy.md).  0: no seeing given, no such correction.
        **algorithm: overrides of ``config/algorithm.yaml``: the solver's (outer_iterations,
            feedback_gain, compensation_sequence, boundary_px, oversample, jmax,
            tolerance_nm, inner_iterations, register_rim, feedback_basis, design_tile_deg)
            and those of its ``input_checks`` (plateau_check, swap_check, ... see
            :class:`.checks.CheckConfig`).

    Returns:
        A :class:`WavefrontResult`; ``.zernikes_nm`` holds Z4..Z22 in nm.

    Raises:
        ImageError (a subclass naming the problem) for unusable images: non-finite, flat,
        cut, too small, mismatched, saturated (``reason`` "saturated") or an exchanged
        intra/extra pair ("swapped"); ConfigError for invalid parameters or configuration.
    """
    t0 = time.perf_counter()
    cfg = EstimateConfig.from_options(
        field_intra_deg=field_intra_deg, field_extra_deg=field_extra_deg,
        instrument=instrument, band=band, wavelength_nm=wavelength_nm,
        defocal_offset_mm=defocal_offset_mm, solver=solver,
        saturation_level=saturation_level, seeing_fwhm_arcsec=seeing_fwhm_arcsec,
        **algorithm)
    a_in, a_ex = _check_pair_shapes(intra, extra)
    _check_donut_fits(a_in.shape, cfg)
    geom, geom_time_s = _geometry(cfg)
    donuts, swap = _prepare_donuts(a_in, a_ex, cfg, geom)
    loop = _outer_loop(geom, _loop_inputs(donuts, cfg, geom), cfg.algorithm, initial_nm)
    return _result(cfg, geom, donuts, swap, loop,
                   wall_time_s=time.perf_counter() - t0, geometry_time_s=geom_time_s)


# -- step 1: check the inputs -----------------------------------------------------------

@dataclass(frozen=True)
class EstimateConfig:
    """Everything one estimate depends on besides the two images, checked (Fig. 3, input).

    Attributes:
        instrument: the loaded instrument model.
        band, wavelength_nm: the optical band and the wavelength used in it.
        field_intra_deg, field_extra_deg: the two stars' field angles (x, y), deg.
        defocal_offset_mm: |detector offset| of both images.
        saturation_level: pixel value at which the detector saturates (None: unknown).
        seeing_fwhm_arcsec: the images' seeing (0: none given).
        algorithm: the outer loop's and solver's parameters.
        checks: the input checks' parameters.
    """

    instrument: Instrument
    band: str
    wavelength_nm: float
    field_intra_deg: tuple[float, float]
    field_extra_deg: tuple[float, float]
    defocal_offset_mm: float
    saturation_level: float | None
    seeing_fwhm_arcsec: float
    algorithm: AlgorithmConfig
    checks: CheckConfig

    @classmethod
    def from_options(cls, *, field_intra_deg: Any, field_extra_deg: Any,
                     instrument: str | Instrument = "lsst", band: str = "r",
                     wavelength_nm: float | None = None,
                     defocal_offset_mm: float | None = None, solver: str = "lsq",
                     saturation_level: float | None = None,
                     seeing_fwhm_arcsec: float = 0.0, **algorithm: Any) -> EstimateConfig:
        """The options of :func:`estimate_wavefront`, checked in a fixed order; ConfigError
        names the first one that is invalid.  ``algorithm`` holds overrides of both the
        solver's parameters and the input checks'."""
        inst = load_instrument(instrument)
        checks = load_checks(**{k: algorithm.pop(k) for k in list(algorithm)
                                if k in _CHECK_KEYS})
        algo = load_algorithm(solver, **algorithm)
        sat = inst.saturation_level if saturation_level is None else saturation_level
        if sat is not None and not (isinstance(sat, (int, float)) and np.isfinite(sat)):
            raise ConfigError(f"saturation_level must be a finite number or None, got {sat!r}")
        seeing = check_seeing(seeing_fwhm_arcsec)
        fi = _field(field_intra_deg, "field_intra_deg")
        fe = _field(field_extra_deg, "field_extra_deg")
        inst.check_field(fi, "field_intra_deg")
        inst.check_field(fe, "field_extra_deg")
        defocus = inst.checked_defocal_offset_mm(
            inst.defocal_offset_mm if defocal_offset_mm is None else defocal_offset_mm)
        if inst.mapping == "batoid" and band not in inst.band_wavelength_nm:
            raise ConfigError(f"unknown band {band!r}; known: {sorted(inst.band_wavelength_nm)}")
        wl = inst.wavelength_nm(band, wavelength_nm)
        return cls(inst, band, wl, fi, fe, defocus, sat, seeing, algo, checks)


def _check_pair_shapes(intra: np.ndarray, extra: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two images as arrays; the TIE signal (§2.1: their difference) needs them the
    same shape."""
    a_in, a_ex = np.asarray(intra), np.asarray(extra)
    if a_in.shape != a_ex.shape:
        raise ShapeMismatchError(
            f"intra and extra images differ in shape: {a_in.shape} vs {a_ex.shape}"
        )
    return a_in, a_ex


def _check_donut_fits(shape: tuple[int, ...], cfg: EstimateConfig) -> None:
    """StampTooSmallError before any geometry is built when even the paraxial donut
    (smaller than the traced one, which the donut checks measure) cannot fit the stamp: the
    pupil grid grows with the donut, and a defocal offset of tens of mm would build one of
    gigabytes before the stamp was found too small."""
    r_d = cfg.instrument.donut_radius_px(cfg.defocal_offset_mm)
    if len(shape) == 2 and 2.0 * r_d > min(shape):
        raise StampTooSmallError(
            f"stamp {shape[1]}x{shape[0]} px is too small: it cannot hold a donut of radius "
            f"{r_d:.0f} px "
            f"({cfg.instrument.name} at a defocal offset of {cfg.defocal_offset_mm:g} mm): "
            "check the defocal offset and the instrument")


# -- step 2: prepare the donuts ---------------------------------------------------------

def _geometry(cfg: EstimateConfig) -> tuple[PairGeometry, float]:
    """The pair's geometry (:func:`pair_geometry`, cached) and the time spent building it
    in this call (0 when it came from the cache)."""
    hits = pair_geometry.cache_info().hits
    geom = pair_geometry(cfg.instrument, cfg.band, cfg.wavelength_nm, cfg.field_intra_deg,
                         cfg.field_extra_deg, cfg.defocal_offset_mm, cfg.algorithm)
    return geom, 0.0 if pair_geometry.cache_info().hits > hits else geom.build_time_s


def _prepare_donuts(a_in: np.ndarray, a_ex: np.ndarray, cfg: EstimateConfig,
                    geom: PairGeometry) -> tuple[tuple[PreparedDonut, PreparedDonut],
                                                 SwapScore | None]:
    """Both stamps checked and measured (:func:`.donuts.prepare_donut`), and the pair
    checked for exchanged images.

    The donut plus its blurred edge must lie inside the stamp; the computation region may
    extend beyond it (samples outside a stamp read zero flux, which is what is there).  Off
    axis the vignetting (§3.3) tells which image is which: an exchanged pair gives a wrong
    wavefront with no other sign of trouble (:mod:`.checks`).  Returns the two prepared
    donuts and the swap check's outcome (None when it did not run).
    """
    margin_px = 2.0 + cfg.algorithm.smooth_sigma_px
    don_in, don_ex = (prepare_donut(a, name=name, outer_radius_px=geom.outer_radius_px,
                                    margin_px=margin_px, saturation_level=cfg.saturation_level,
                                    checks=cfg.checks)
                      for a, name in ((a_in, "intra"), (a_ex, "extra")))
    swap = None
    if cfg.checks.swap_check and geom.footprints is not None:
        centroids, noise = (don_in.centroid_xy, don_ex.centroid_xy), (don_in.noise, don_ex.noise)
        fp = geom.footprints
        windows = stamp_windows(don_in.image, don_ex.image, centroids, noise, fp.size)
        swap = check_not_swapped(don_in.image, don_ex.image, *centroids, noise, fp,
                                 cfg.checks, windows)
        # One half turned or mirrored, on the same footprints (after the swap check: a pair
        # exchanged, or both halves turned by 180 degrees, is named as such first).
        check_orientation(don_in.image, don_ex.image, centroids, noise, fp, cfg.checks,
                          windows)
    return (don_in, don_ex), swap


@dataclass(frozen=True)
class _LoopInputs:
    """What the outer loop reads of the two images (Fig. 3, box a).

    Attributes:
        images: the intra and extra stamps, smoothed, float32.
        base_xy: each image's flux centroid less the mapping's model centroid for W = 0
            (px): where the mapping's reference point falls in the stamp.
        blur_ref: the edge signal of the images' blur in the weighted difference image
            (:mod:`.blur`), or None.
    """

    images: tuple[np.ndarray, np.ndarray]
    base_xy: tuple[np.ndarray, np.ndarray]
    blur_ref: np.ndarray | None


def _loop_inputs(donuts: tuple[PreparedDonut, PreparedDonut], cfg: EstimateConfig,
                 geom: PairGeometry) -> _LoopInputs:
    """Smoothed images, their alignment to the mappings, and the blur's edge signal.

    Alignment: each image is placed so that its centroid falls where the mapping, with the
    current wavefront, puts the flux centroid of its illuminated pupil.  The wavefront moves
    that centroid by C * mean(grad W) over the pupil (§2.1: x' = x + C dW/dx), which is not
    zero for coma, nor for any term on a vignetted pupil, and differs between the two halves
    of a split sensor (§3.4).  Tip/tilt itself then has no effect; it is solved for as a
    nuisance term and dropped.

    Smoothing: a light Gaussian blur makes the images smooth on the scale of the pupil
    sampling, so that point-sampling them (compensation) integrates flux without a
    dependence on where the samples fall inside pixels (unblurred: up to 13 nm of Z4).
    """
    algo = cfg.algorithm
    don_in, don_ex = donuts
    base_in = np.array(don_in.centroid_xy) - geom.centroid_model_intra
    base_ex = np.array(don_ex.centroid_xy) - geom.centroid_model_extra
    img_in, img_ex = don_in.image, don_ex.image
    if algo.smooth_sigma_px > 0:
        img_in = gaussian_filter(img_in, algo.smooth_sigma_px, mode="constant")
        img_ex = gaussian_filter(img_ex, algo.smooth_sigma_px, mode="constant")
    img_in = img_in.astype(np.float32)
    img_ex = img_ex.astype(np.float32)
    blur_ref = None
    if algo.blur_reference and cfg.seeing_fwhm_arcsec > 0:
        # The images' blur beyond the pixels: the seeing and the smoothing above.  Without a
        # seeing (0: none given) no blur model is subtracted (docs/accuracy.md).
        inst = cfg.instrument
        blur_px = image_blur_sigma_px(cfg.seeing_fwhm_arcsec, algo.smooth_sigma_px,
                                      inst.pixel_size_um, inst.focal_length_m)
        blur_ref = geom.blur_reference(blur_px, img_in.shape)
    return _LoopInputs((img_in, img_ex), (base_in, base_ex), blur_ref)


# -- step 3: the outer loop (§2.1, Fig. 3 boxes a-e) ------------------------------------

@dataclass(frozen=True)
class _LoopOutcome:
    """The outer loop's result.

    Attributes:
        estimate: departure from design Z1..Z_jmax (nm) after the last good iteration
            (zeros if the first compensation already folded).
        history: the estimate after each iteration.
        residual_rms: rms over Z4..Z_jmax of each iteration's residual (nm).
        caustic: the compensation folded into caustic; ``estimate`` is the last good one.
        converged: the last update fell below the tolerance before the iteration limit.
        compensated: the last good compensated (intra, extra) intensities, or None.
    """

    estimate: np.ndarray
    history: list[np.ndarray]
    residual_rms: list[float]
    caustic: bool
    converged: bool
    compensated: tuple[np.ndarray, np.ndarray] | None


def _loop_start(algo: AlgorithmConfig, initial_nm: np.ndarray | None
                ) -> tuple[np.ndarray, list[int], float]:
    """(W_comp, schedule, gain) of the outer loop's first iteration.

    From zero (§2.1): the compensation schedule ramps up the highest compensated Noll index
    (4, 4, 6, 6, 13, ...) with the feedback gain.  Warm started from ``initial_nm``: the full
    jmax from the first iteration with ``warm_start_gain``, as the start is already near the
    fixed point.  Piston, tip and tilt are never compensated.
    """
    jmax = algo.jmax
    w_comp = np.zeros(jmax)
    schedule = algo.schedule()
    gain = algo.feedback_gain
    if initial_nm is not None:
        start = np.asarray(initial_nm, dtype=float).ravel()[:jmax]
        if not np.all(np.isfinite(start)):
            raise ConfigError("initial_nm must be finite")
        w_comp[:start.size] = start
        w_comp[:3] = 0.0
        schedule = [jmax] * algo.outer_iterations
        gain = algo.warm_start_gain
    return w_comp, schedule, gain


def _outer_loop(geom: PairGeometry, inputs: _LoopInputs, algo: AlgorithmConfig,
                initial_nm: np.ndarray | None) -> _LoopOutcome:
    """The outer loop of Fig. 3 (§2.1): compensate both images for W_comp (box b), solve the
    TIE for the residual (box c), take ``W_comp + W_res`` as the estimate, and feed back
    ``gain * W_res`` up to the schedule's Noll index (boxes d-e).

    Stops when the full jmax is compensated, the residual rms is below ``tolerance_nm`` and
    the rim registration no longer moves the images; or, keeping the last good estimate,
    when a compensation folds into caustic (§2.1).
    """
    w_comp, schedule, gain = _loop_start(algo, initial_nm)
    base_xy = inputs.base_xy
    estimate = w_comp.copy()
    history: list[np.ndarray] = []
    res_rms: list[float] = []
    caustic = converged = False
    last = None
    for j_stage in schedule:
        c_in, c_ex = _compensate_pair(geom, inputs.images, base_xy, w_comp)
        if c_in.caustic or c_ex.caustic:
            caustic = True
            break
        last = (c_in.intensity, c_ex.intensity)
        base_xy, shift_px = _register_on_rim(geom, c_in.intensity, c_ex.intensity, base_xy)
        w_res = _solve_residual(geom, c_in.intensity, c_ex.intensity, inputs.blur_ref)
        estimate = w_comp + w_res
        history.append(estimate.copy())
        rms = float(np.sqrt(np.mean(w_res[3:] ** 2)))
        res_rms.append(rms)
        if j_stage >= algo.jmax and rms < algo.tolerance_nm and shift_px < 0.01:
            converged = True
            break
        w_comp = w_comp + gain * _feedback_step(geom, w_res, j_stage)
        w_comp[:3] = 0.0
    if not history:
        # Caustic already at the first compensation: nothing trustworthy was estimated.
        estimate = np.zeros(algo.jmax)
    return _LoopOutcome(estimate, history, res_rms, caustic, converged, last)


def _compensate_pair(geom: PairGeometry, images: tuple[np.ndarray, np.ndarray],
                     base_xy: tuple[np.ndarray, np.ndarray], w_comp: np.ndarray
                     ) -> tuple[Compensated, Compensated]:
    """Both images remapped to the pupil for the wavefront ``w_comp`` (§2.1: the
    mapping x' = x + C grad W and its Jacobian; Fig. 3 box b).

    Each image's reference point moves with the centroid shift the compensated wavefront
    causes (``C * mean(grad W)``, see :func:`_loop_inputs`).
    """
    derivs = geom.basis.derivative_fields(w_comp)
    m_in, m_ex = geom.mapping_intra, geom.mapping_extra
    centre_in = base_xy[0] - m_in.c_px_per_nm * (geom.mean_gradient_intra @ w_comp)
    centre_ex = base_xy[1] - m_ex.c_px_per_nm * (geom.mean_gradient_extra @ w_comp)
    return (compensate(images[0], centre_in, m_in, derivs),
            compensate(images[1], centre_ex, m_ex, derivs))


def _register_on_rim(geom: PairGeometry, i_in: np.ndarray, i_ex: np.ndarray,
                     base_xy: tuple[np.ndarray, np.ndarray]
                     ) -> tuple[tuple[np.ndarray, np.ndarray], float]:
    """Pupil registration on the primary's outer rim (beyond the paper; see
    :func:`_rim_registration`): the pupil shift measured on the mean compensated image,
    undone from the next iteration on by moving each image by its mapping's mean Jacobian
    times the shift.  Returns the new reference points and the largest image move (px; 0
    when there is no rim band or too little light on it)."""
    if geom.rim_pinv is None:
        return base_xy, 0.0
    rim = 0.5 * (i_in[geom.rim_index] + i_ex[geom.rim_index])
    level, ax, ay = (geom.rim_pinv @ rim).astype(float)
    if level <= 0.2:
        return base_xy, 0.0
    shift = np.array([ax, ay]) / level
    moved = (base_xy[0] + geom.jac_mean_intra @ shift, base_xy[1] + geom.jac_mean_extra @ shift)
    return moved, float(np.abs(geom.jac_mean_intra @ shift).max())


def _solve_residual(geom: PairGeometry, i_in: np.ndarray, i_ex: np.ndarray,
                    blur_ref: np.ndarray | None) -> np.ndarray:
    """The residual wavefront Z1..Z_jmax (nm) of the compensated images (box c): the TIE
    (§2, eq. 1) solved for the weighted difference image (§2.1's signal, on the common pupil
    of §3.4) less the blur's own edge signal.  Piston has no signal, and tip/tilt is taken
    out by the alignment: both are set to zero."""
    d_i = (i_in - i_ex) * geom.weight
    if blur_ref is not None:
        d_i -= blur_ref
    w_res = geom.solver.solve(d_i, geom.kappa)
    w_res[:3] = 0.0
    return w_res


def _feedback_step(geom: PairGeometry, w_res: np.ndarray, j_stage: int) -> np.ndarray:
    """The residual truncated to Noll indices <= ``j_stage`` (§2.1: low orders first, to
    decouple terms of the same azimuthal frequency).

    With the orthonormal feedback basis the truncation is made in the basis orthonormal on
    the vignetted common pupil (§3.3): ``u = L^T w``; L^T is upper triangular, so the step
    stays within Z1..Z_{j_stage}.
    """
    idx = np.arange(1, w_res.size + 1)
    if geom.feedback_l is None:
        return np.where(idx <= j_stage, w_res, 0.0)
    u = geom.feedback_l.T @ w_res
    u[idx > j_stage] = 0.0
    return solve_triangular(geom.feedback_l.T, u, lower=False)


# -- step 4: the result (§3.4: the design wavefront added back) -------------------------

def _swap_outcome(swap: SwapScore | None, checks: CheckConfig) -> str:
    """``"off"``, ``"confirmed"`` or ``"inconclusive"`` (see :attr:`WavefrontResult.swap_check`)."""
    if swap is None:
        return "off"
    if (swap.preference[1] > checks.swap_threshold
            and swap.significance[1] > checks.swap_min_significance):
        return "confirmed"
    return "inconclusive"


def _result(cfg: EstimateConfig, geom: PairGeometry,
            donuts: tuple[PreparedDonut, PreparedDonut], swap: SwapScore | None,
            loop: _LoopOutcome, *, wall_time_s: float,
            geometry_time_s: float) -> WavefrontResult:
    """The total wavefront at the mid-point field: the loop's departure from design plus the
    design wavefront there (§3.3-3.4), with the masks and compensated images for display."""
    jmax = cfg.algorithm.jmax
    total = loop.estimate + np.asarray(geom.intrinsic_nm)
    total[:3] = 0.0
    comp = {}
    if loop.compensated is not None:
        comp = {"intra": geom.pupil_image(loop.compensated[0]),
                "extra": geom.pupil_image(loop.compensated[1])}
    masks = {
        "intra": geom.pupil_image(geom.mask_intra.astype(float), 0.0) > 0,
        "extra": geom.pupil_image(geom.mask_extra.astype(float), 0.0) > 0,
        "common": geom.pupil_image(geom.mask_common.astype(float), 0.0) > 0,
        "region": geom.pupil_image(np.ones(geom.region.size), 0.0) > 0,
    }
    n_iter = len(loop.history)
    return WavefrontResult(
        zernikes_nm=total[3:22].copy(),
        zernikes_all_nm=total,
        intrinsic_nm=np.asarray(geom.intrinsic_nm)[3:22].copy(),
        caustic=loop.caustic,
        converged=loop.converged,
        iterations=n_iter,
        history_nm=np.array(loop.history).reshape(n_iter, jmax),
        residual_rms_nm=np.array(loop.residual_rms),
        field_deg=geom.field_mid_deg,
        wall_time_s=wall_time_s,
        geometry_time_s=geometry_time_s,
        solver=cfg.algorithm.solver,
        instrument=cfg.instrument.name,
        band=cfg.band,
        wavelength_nm=cfg.wavelength_nm,
        masks=masks,
        compensated=comp,
        inputs={"intra": donuts[0], "extra": donuts[1]},
        departure_all_nm=np.concatenate([[0.0, 0.0, 0.0], loop.estimate[3:]]),
        swap_check=_swap_outcome(swap, cfg.checks),
    )
