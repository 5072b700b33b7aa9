"""The cached field-independent ray-hit fit (cwfs_ros.wfs.mapping._FitOperator).

A new star field must cost one ray trace plus small matrix products, and give the same
mapping and the same estimate as a fit solved from scratch.  The expected values here come
from the raw ray trace and an independent ``numpy.linalg.lstsq`` fit, not from the cached
operator.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from cwfs_ros.config import config_dir
from cwfs_ros.wfs import estimate_wavefront, load_instrument
from cwfs_ros.wfs import mapping as mp
from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry
from cwfs_ros.wfs.zernike import zernike_basis

R00 = yaml.safe_load((config_dir() / "sensors" / "lsst_corners.yaml").read_text())["corners"]["R00"]
FI0, FE0 = np.array(R00["intra"]["field_deg"]), np.array(R00["extra"]["field_deg"])
WL = 622.0


def _pupil_points() -> tuple[np.ndarray, np.ndarray]:
    """A pupil grid like the estimator's (annulus plus a boundary), 1/61 per sample."""
    n, sp = 147, 1.0 / 61.0
    ax = (np.arange(n) - (n - 1) / 2.0) * sp
    gx, gy = np.meshgrid(ax, ax)
    r = np.hypot(gx, gy).ravel()
    keep = (r <= 1.19) & (r >= 0.50)
    return gx.ravel()[keep], gy.ravel()[keep]


def _reference_fit(x, y, hx, hy, ok):
    """Independent least-squares fit of the ray hits (order 14 circle Zernikes)."""
    rmax = float(np.sqrt((x * x + y * y).max())) * 1.0001
    b = zernike_basis(x / rmax, y / rmax, jmax=120, eps=0.0)
    idx = np.flatnonzero(ok)[::3]
    coef, *_ = np.linalg.lstsq(b.z[:, idx].T, np.stack([hx[idx], hy[idx]], 1), rcond=None)
    cx, cy = coef[:, 0], coef[:, 1]
    return (cx @ b.z, cy @ b.z, cx @ b.dx / rmax, cx @ b.dy / rmax, cy @ b.dx / rmax,
            cy @ b.dy / rmax)


def test_fast_fit_matches_direct_trace_at_random_fields() -> None:
    inst = load_instrument("lsst")
    x, y = _pupil_points()
    rng = np.random.default_rng(11)
    for k in range(3):
        side = ("intra", "extra")[k % 2]
        f0 = FI0 if side == "intra" else FE0
        fld = tuple(float(v) for v in f0 + rng.uniform([-0.03, -0.06], [0.03, 0.06]))
        m = mp.nominal_mapping(inst, side, x, y, defocus_mm=1.5, band="r", wavelength_nm=WL,
                               field_deg=fld)
        hx, hy, ok, transmitted = mp._trace_defocused(inst, "r", WL, fld, side, 1.5, x, y)
        # Against the raw ray hits: the fit is far inside 1e-3 px on the annulus.
        r2 = x * x + y * y
        ann = (r2 <= 1.0) & (r2 >= inst.obscuration**2)
        assert np.abs(m.x_px - hx)[ok & ann].max() < 2e-3
        assert np.abs(m.y_px - hy)[ok & ann].max() < 2e-3
        # Against an independent fit solved from scratch: equal to rounding.
        fx, fy, jxx, _, _, jyy = _reference_fit(x, y, hx, hy, ok)
        assert np.abs(m.x_px - fx).max() < 1e-6 and np.abs(m.y_px - fy).max() < 1e-6
        assert np.abs(m.jxx - jxx).max() < 1e-5 and np.abs(m.jyy - jyy).max() < 1e-5
        np.testing.assert_array_equal(m.transmitted, transmitted & ann)


def test_fit_operator_is_built_once_per_pupil_grid() -> None:
    inst = load_instrument("lsst")
    x, y = _pupil_points()
    kw = dict(defocus_mm=1.5, band="r", wavelength_nm=WL)
    mp.nominal_mapping(inst, "intra", x, y, field_deg=tuple(FI0), **kw)
    builds = mp.fit_operator_builds
    op = mp._fit_operator(x, y)
    for d in (0.01, -0.02, 0.03):
        mp.nominal_mapping(inst, "intra", x, y, field_deg=(FI0[0] + d, FI0[1] - d), **kw)
        mp.nominal_mapping(inst, "extra", x, y, field_deg=(FE0[0] - d, FE0[1] + d), **kw)
    assert mp.fit_operator_builds == builds  # new fields reuse the operator
    assert mp._fit_operator(x.copy(), y.copy()) is op  # keyed by the points' values
    mp._fit_operator(x[1:], y[1:])  # other points: another operator
    assert mp.fit_operator_builds == builds + 1


def test_fit_with_failed_rays_falls_back_to_a_direct_solve() -> None:
    x, y = _pupil_points()
    op = mp._fit_operator(x, y)
    rng = np.random.default_rng(2)
    hx, hy = 60.0 * x + 0.3 * x * y, -61.0 * y + 0.2 * x * x
    ok = rng.random(x.size) > 0.01
    hx[~ok] = 1e6  # garbage where rays failed must not enter the fit
    coef = op.coefficients(hx, hy, ok)
    np.testing.assert_allclose(coef.T @ op.z, np.stack([60.0 * x + 0.3 * x * y,
                                                        -61.0 * y + 0.2 * x * x]), atol=1e-8)


@pytest.mark.parametrize("solver", ["lsq"])
def test_estimate_equals_the_from_scratch_fit(monkeypatch: pytest.MonkeyPatch,
                                              solver: str) -> None:
    """One ray-traced pair at random corner fields: the same Zernikes as a direct fit."""
    from cwfs_ros.sim.render import render_donut
    from cwfs_ros.sim.telescope import perturbed_telescope

    rng = np.random.default_rng(5)
    fi = tuple(float(v) for v in FI0 + rng.uniform([-0.03, -0.06], [0.03, 0.06]))
    fe = tuple(float(v) for v in FE0 + rng.uniform([-0.03, -0.06], [0.03, 0.06]))
    dof = np.zeros(50)
    dof[5] = 15.0
    tel = perturbed_telescope(dof, band="r")
    intra, extra = (render_donut(tel, f, dz, wavelength_nm=WL, npix=160, n_photons=1e6,
                                 rng=rng, poisson=False) for f, dz in ((fi, -1.5), (fe, 1.5)))
    pair_geometry.cache_clear()
    fast = estimate_wavefront(intra, extra, field_intra_deg=fi, field_extra_deg=fe,
                              solver=solver)

    def direct(inst, side, defocus_mm, x, y, band, wavelength_nm, field_deg, tile_deg=0.0):
        hx, hy, ok, transmitted = mp._trace_defocused(inst, band, wavelength_nm, field_deg,
                                                      side, defocus_mm, x, y)
        parts = _reference_fit(x, y, hx, hy, ok)
        return parts, transmitted, 0.0

    monkeypatch.setattr(mp, "_batoid", direct)
    pair_geometry.cache_clear()
    try:
        ref = estimate_wavefront(intra, extra, field_intra_deg=fi, field_extra_deg=fe,
                                 solver=solver)
    finally:
        pair_geometry.cache_clear()
    assert np.abs(fast.zernikes_nm - ref.zernikes_nm).max() < 0.5
    assert np.abs(ref.zernikes_nm).max() > 20  # a real signal, not two zeros
    assert load_algorithm(solver).jmax == fast.zernikes_all_nm.size


def test_design_tiles_match_the_direct_trace_and_are_reused() -> None:
    """Interpolated design Zernikes vs batoid's own fit at random corner mid-points."""
    import batoid

    from cwfs_ros.sim.telescope import load_lsst

    inst = load_instrument("lsst")
    tel = load_lsst("r")
    mid = np.array(R00["mid_deg"])
    rng = np.random.default_rng(4)
    mp.design_zernikes_tiled(inst, "r", WL, tuple(mid), 22, 0.125)
    builds = mp.design_tile_builds
    for _ in range(3):
        fx, fy = (float(v) for v in mid + rng.uniform([-0.03, -0.05], [0.03, 0.05]))
        tiled = mp.design_zernikes_tiled(inst, "r", WL, (fx, fy), 22, 0.125)
        direct = batoid.zernike(tel, np.deg2rad(fx), np.deg2rad(fy), WL * 1e-9, jmax=22,
                                eps=inst.obscuration, nx=128)[1:] * WL
        assert np.abs(tiled - direct)[3:].max() < 0.3
        assert np.abs(direct[3:]).max() > 50  # large design aberrations at the corners
    # The corner's mid-points share one or two tiles, each fitted once (at its third field).
    assert mp.design_tile_builds - builds <= 1
    n = mp.design_tile_builds
    later = (fx + 1e-4, fy)
    value = mp.design_zernikes_tiled(inst, "r", WL, later, 22, 0.125)
    assert mp.design_tile_builds == n
    assert not np.array_equal(value, mp.design_zernikes_nm(inst, "r", WL, later, 22))
    # 0 disables the tiles: the direct trace, bit for bit.
    np.testing.assert_array_equal(mp.design_zernikes_tiled(inst, "r", WL, (fx, fy), 22, 0.0),
                                  mp.design_zernikes_nm(inst, "r", WL, (fx, fy), 22))


def test_distance_transform_dilation_equals_binary_dilation() -> None:
    from scipy.ndimage import binary_dilation

    from cwfs_ros.wfs.estimator import _dilate

    rng = np.random.default_rng(8)
    yy, xx = np.mgrid[:120, :120]
    masks = [rng.random((120, 120)) < 0.002, rng.random((90, 90)) < 0.3,
             np.hypot(xx - 57.3, yy - 61.0) < 37.0, np.zeros((40, 40), bool),
             # a small patch near one edge: the dilation works on its box alone
             np.hypot(xx - 104.2, yy - 9.6) < 5.0]
    for m in masks:
        for r in (1, 2, 3, 4, 5, 6, 7, 12):  # both methods (rectangles up to 6)
            yd, xd = np.mgrid[-r:r + 1, -r:r + 1]
            disk = xd * xd + yd * yd <= r * r
            np.testing.assert_array_equal(_dilate(m, r), binary_dilation(m, structure=disk))


def test_region_neighbours_match_a_walk_over_the_grid() -> None:
    """The padded look-up table gives each region point's four neighbours, and the
    sentinel where a neighbour is off the region or off the grid (the region touches all
    four grid edges here)."""
    from cwfs_ros.wfs.tie import _region_neighbours

    rng = np.random.default_rng(3)
    nr, nc = 7, 9
    grid = rng.random((nr, nc)) < 0.6
    grid[0, 4] = grid[nr - 1, 2] = grid[3, 0] = grid[5, nc - 1] = True
    region = np.flatnonzero(grid)
    m = region.size
    got = _region_neighbours((nr, nc), region)
    for k, flat in enumerate(region):
        r, c = divmod(int(flat), nc)
        for idx, (dr, dc) in zip(got, ((0, -1), (0, 1), (-1, 0), (1, 0)), strict=True):
            r2, c2 = r + dr, c + dc
            inside = 0 <= r2 < nr and 0 <= c2 < nc and grid[r2, c2]
            want = int(np.flatnonzero(region == r2 * nc + c2)[0]) if inside else m
            assert idx[k] == want, (r, c, dr, dc)


def test_response_matrix_is_the_divergence_on_the_grid() -> None:
    """``B_i = div(I grad Z_i)`` by central differences, as the response matrix builds it
    from its region's neighbours (shifted slices left and right), equals the same
    differences taken on the whole grid with the flux displacement zero off the region; a
    guard-band weight zeroes its columns."""
    from scipy.ndimage import gaussian_filter

    from cwfs_ros.wfs.tie import response_matrix

    n, spacing = 40, 1.0 / 17.0
    ax = (np.arange(n) - (n - 1) / 2.0) * spacing
    gx, gy = np.meshgrid(ax, ax)
    r = np.hypot(gx, gy)
    pupil_2d = (r <= 1.0) & (r >= 0.61) & ~((gx > 0.7) & (gy > 0.2))  # a vignetted lune
    region = np.flatnonzero((r <= 1.2) & (r >= 0.45))
    pupil = pupil_2d.ravel()[region]
    basis = zernike_basis(gx.ravel()[region], gy.ravel()[region], jmax=11, eps=0.61,
                          dtype=np.float32)
    rng = np.random.default_rng(5)
    weight = (rng.random(region.size) < 0.9).astype(np.float32)
    got = response_matrix((n, n), spacing, region, basis, pupil, 1.0, weight=weight)

    model = gaussian_filter(pupil_2d.astype(float), 1.0).ravel()[region]
    want = np.zeros_like(got, dtype=np.float64)
    for j in range(1, 11):
        u = np.zeros((n + 2, n + 2))
        v = np.zeros((n + 2, n + 2))
        u[1:-1, 1:-1] = _on_grid(n, region, basis.dx[j] * model)
        v[1:-1, 1:-1] = _on_grid(n, region, basis.dy[j] * model)
        div = (u[1:-1, 2:] - u[1:-1, :-2] + v[2:, 1:-1] - v[:-2, 1:-1]) / (2.0 * spacing)
        want[j - 1] = div.ravel()[region] * weight
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6 * np.abs(want).max())
    assert np.all(got[:, weight == 0] == 0)


def _on_grid(n: int, region: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.zeros(n * n)
    out[region] = values
    return out.reshape(n, n)


def test_geometry_region_and_common_gram() -> None:
    """The computation region is the dilated union of both pupils on the candidate points
    (read from the cached position table), and the Gram matrix over the common pupil (built
    on first use) is the area average of Z_i Z_j there."""
    from scipy.ndimage import binary_dilation

    from cwfs_ros.wfs.zernike import gram_matrix

    inst = load_instrument("lsst")
    algo = load_algorithm("lsq")
    g = pair_geometry(inst, "r", WL, tuple(FI0), tuple(FE0), 1.5, algo)
    n = g.shape[0]
    # Recomputed from the pupil points alone: the grid of _pupil_grid, the masks on it.
    sp = g.spacing
    ax = (np.arange(n) - (n - 1) / 2.0) * sp
    gx, gy = np.meshgrid(ax, ax)
    np.testing.assert_allclose(gx.ravel()[g.region], g.x)
    np.testing.assert_allclose(gy.ravel()[g.region], g.y)
    union = np.zeros(n * n, bool)
    union[g.region] = g.mask_intra | g.mask_extra
    r = algo.boundary_px * algo.oversample
    yd, xd = np.mgrid[-r:r + 1, -r:r + 1]
    grown = binary_dilation(union.reshape(n, n), structure=xd * xd + yd * yd <= r * r).ravel()
    assert np.all(grown[g.region])  # every region point is within the boundary ...
    outside = np.flatnonzero(grown & ~np.isin(np.arange(n * n), g.region))
    # ... and every dilated point left out is off the candidate annulus (beyond its extent).
    assert np.all(np.hypot(gx.ravel()[outside], gy.ravel()[outside]) > 1.08)
    np.testing.assert_allclose(np.asarray(g.gram_common)[3:22, 3:22],
                               gram_matrix(g.basis, g.mask_common), rtol=1e-5, atol=1e-6)


def test_map_tiles_match_the_direct_trace_and_are_reused() -> None:
    """Field-tiled batoid mapping vs the direct trace at random fields of one half-chip."""
    inst = load_instrument("lsst")
    x, y = _pupil_points()
    kw = dict(defocus_mm=1.5, band="r", wavelength_nm=WL)
    r2 = x * x + y * y
    ann = (r2 <= 1.0) & (r2 >= inst.obscuration**2)
    rng = np.random.default_rng(9)
    # Fields inside one tile: the first two are traced directly, the tile is fitted at the
    # third, and later fields reuse it.
    t = 0.125
    lo = np.floor(FE0 / t) * t
    fields = [tuple(float(v) for v in lo + rng.uniform(0.01, t - 0.01, 2)) for _ in range(5)]
    builds = None
    for k, fld in enumerate(fields):
        tiled = mp.nominal_mapping(inst, "extra", x, y, field_deg=fld, tile_deg=t, **kw)
        direct = mp.nominal_mapping(inst, "extra", x, y, field_deg=fld, **kw)
        if k == 2:
            builds = mp.map_tile_builds
        assert np.abs(tiled.x_px - direct.x_px)[ann].max() < 1e-5
        assert np.abs(tiled.y_px - direct.y_px)[ann].max() < 1e-5
        assert np.abs(tiled.jxx - direct.jxx).max() < 1e-4
        np.testing.assert_array_equal(tiled.transmitted, direct.transmitted)
        assert (~tiled.transmitted[ann]).any()  # vignetted: the masks are a real check
    assert mp.map_tile_builds == builds


def _tiled_and_direct(monkeypatch: pytest.MonkeyPatch, side: str, fields: list, x, y,
                      traced: list[int]) -> list[tuple]:
    """Tiled and direct masks at ``fields`` of one tile; ``traced`` collects the sizes of
    the tiled path's ray traces per field."""
    inst = load_instrument("lsst")
    kw = dict(defocus_mm=1.5, band="r", wavelength_nm=WL)
    real_trace = mp._trace_defocused
    out = []
    for fld in fields:
        calls: list[int] = []

        def counting(*args, calls=calls):
            calls.append(args[-1].size)
            return real_trace(*args)

        monkeypatch.setattr(mp, "_trace_defocused", counting)
        tiled = mp.nominal_mapping(inst, side, x, y, field_deg=fld, tile_deg=0.125, **kw)
        monkeypatch.setattr(mp, "_trace_defocused", real_trace)
        direct = mp.nominal_mapping(inst, side, x, y, field_deg=fld, **kw)
        traced.append(sum(calls))
        out.append((tiled.transmitted, direct.transmitted))
    return out


def _tile_fields(f0: np.ndarray, n: int, rng: np.random.Generator) -> list[tuple]:
    lo = np.floor(f0 / 0.125) * 0.125
    return [tuple(float(v) for v in lo + rng.uniform(0.01, 0.115, 2)) for _ in range(n)]


def test_tile_vignetting_from_aperture_edges_matches_the_direct_trace(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Inside a map tile the swept band is decided from interpolated ray positions on the
    apertures, with (almost) no ray traced; the masks must be those of the direct trace."""
    x, y = _pupil_points()
    x.setflags(write=False)
    y.setflags(write=False)
    rng = np.random.default_rng(21)
    for side, f0 in (("intra", FI0), ("extra", FE0)):
        traced: list[int] = []
        pairs = _tiled_and_direct(monkeypatch, side, _tile_fields(f0, 8, rng), x, y, traced)
        for tiled, direct in pairs:
            np.testing.assert_array_equal(tiled, direct)
        key = next(k_ for k_ in mp._MAP_TILE_CACHE if k_[1] == side
                   and k_[5] == mp.tile_of(_tile_fields(f0, 1, rng)[0], 0.125))
        _, always, sweep, edges, _ = mp._MAP_TILE_CACHE[key]
        assert edges is not None and sweep.size > 500  # a real vignetting band
        # The tile is built at the third field and serves the next five: at most a few
        # points near an edge are traced for each (tracing the band would be > 500 rays).
        assert max(traced[3:]) <= 10


def test_aperture_margins_follow_batoid_obscurations() -> None:
    """The margin rule (mp._aperture, mp._edge_margin) against batoid's own ``contains``."""
    import batoid

    rng = np.random.default_rng(3)
    px, py = rng.uniform(-2.5, 2.5, (2, 20000))
    for obsc in (batoid.ObscNegation(batoid.ObscCircle(1.2, x=0.3, y=-0.2)),
                 batoid.ObscNegation(batoid.ObscAnnulus(0.7, 1.9, x=-0.1)),
                 batoid.ObscCircle(0.8, y=0.4),
                 batoid.ObscAnnulus(0.5, 1.0)):
        passes = mp._edge_margin(px, py, np.array(mp._aperture(obsc))) > 0
        np.testing.assert_array_equal(passes, ~obsc.contains(px, py))
    assert mp._aperture(batoid.ObscRectangle(1.0, 2.0)) is None


def test_tile_without_an_edge_model_traces_its_band(monkeypatch: pytest.MonkeyPatch) -> None:
    """An optic with an aperture that is not a circle or annulus gets no edge model: the
    tile traces its whole swept band per star, with the same masks."""
    monkeypatch.setattr(mp, "_MAP_TILE_CACHE", {})
    monkeypatch.setattr(mp, "_map_tile_requests", {})
    monkeypatch.setattr(mp, "_aperture", lambda obscuration: None)
    x, y = _pupil_points()
    traced: list[int] = []
    pairs = _tiled_and_direct(monkeypatch, "extra", _tile_fields(FE0, 4, np.random.default_rng(4)),
                              x, y, traced)
    for tiled, direct in pairs:
        np.testing.assert_array_equal(tiled, direct)
    (_, always, sweep, edges, _), = mp._MAP_TILE_CACHE.values()
    assert edges is None
    assert traced[3] == sweep.size > 500


def test_an_instruments_kept_hash_does_not_travel_to_another_process() -> None:
    """An instrument keeps its hash once made (it keys the geometry caches), but a pickled
    one hashes in a worker process as that process's own equal instrument does: string
    hashes differ between processes, and equal keys must find each other."""
    import os
    import pickle
    import subprocess
    import sys

    inst = load_instrument("lsst")
    assert hash(inst) == hash(load_instrument("lsst"))
    code = ("import pickle, sys\n"
            "from cwfs_ros.wfs import load_instrument\n"
            "a = pickle.loads(sys.stdin.buffer.read())\n"
            "print(hash(a) == hash(load_instrument('lsst')), a == load_instrument('lsst'))\n")
    env = {**os.environ, "PYTHONHASHSEED": "random"}
    out = subprocess.run([sys.executable, "-c", code], input=pickle.dumps(inst),
                         capture_output=True, check=True, env=env, timeout=120)
    assert out.stdout.split() == [b"True", b"True"], out


def test_central_gradient_and_one_field_monomials_are_numpys() -> None:
    """The rim registration's gradient at chosen points is np.gradient's there, inside the
    grid and at its edge; one field's tile monomials are those of the same field given as
    arrays, to the bit."""
    from cwfs_ros.wfs.estimator import _central_gradient

    rng = np.random.default_rng(4)
    n, spacing = 30, 0.07
    f = rng.normal(size=n * n)
    gy, gx = np.gradient(f.reshape(n, n), spacing)
    inner = np.array([n + 1, 5 * n + 7, (n - 2) * n + n - 2])
    edge = np.array([0, 3 * n, n * n - 1])
    for idx in (inner, np.concatenate([inner, edge])):
        got_x, got_y = _central_gradient(f, n, idx, spacing)
        np.testing.assert_array_equal(got_x, gx.ravel()[idx])
        np.testing.assert_array_equal(got_y, gy.ravel()[idx])

    u, v = rng.uniform(-1, 1, 400), rng.uniform(-1, 1, 400)
    batch = mp._tile_monomials(u, v)
    for k in range(u.size):
        np.testing.assert_array_equal(mp._tile_monomials(np.array(u[k]), np.array(v[k])),
                                      batch[k])
