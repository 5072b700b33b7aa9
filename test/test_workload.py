"""The workers' workload: cost-balanced assignment, the visit-timeout promise, cache reports
(cwfs_ros.runtime.workload), and warmed field tiles (cwfs_ros.wfs.mapping.warm_field_tiles).

Expected assignments and loads are worked out by hand from the costs given; tile counts
come from the tile grid (0.125 deg), not from the code under test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cwfs_ros.runtime.workload import WorkloadMonitor, balanced_affinity
from cwfs_ros.wfs import mapping as mp
from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry, reset_caches, warm_star_fields
from cwfs_ros.wfs.instrument import load_instrument

ROUND_ROBIN = {"R00": 0, "R04": 1, "R40": 0, "R44": 1}


def _monitor(costs_ms: dict[str, float], n: int = 5) -> WorkloadMonitor:
    m = WorkloadMonitor()
    for _ in range(n):
        for c, v in costs_ms.items():
            m.record(c, v, 1, None)
    return m


def test_balanced_affinity_puts_the_largest_costs_apart() -> None:
    # LPT by hand: R40 (3) -> 0, R00 (2) -> 1, R44 (1.5) -> 1 (load 2 < 3), R04 (1) -> 1?
    # after R44 worker 1 holds 3.5 > 3, so R04 goes to 0.
    costs = {"R00": 2.0, "R04": 1.0, "R40": 3.0, "R44": 1.5}
    assert balanced_affinity(costs, 2) == {"R40": 0, "R00": 1, "R44": 1, "R04": 0}
    # Equal costs: names break the ties, the same answer every time.
    equal = dict.fromkeys(("R44", "R00", "R40", "R04"), 1.0)
    assert balanced_affinity(equal, 2) == ROUND_ROBIN
    assert balanced_affinity(equal, 2) == balanced_affinity(dict(reversed(equal.items())), 2)


def test_a_corner_moves_only_for_a_fifth_less_load() -> None:
    # Round robin puts the two heavy corners (R00, R40) on worker 0: 1.6 s against 0.4 s.
    m = _monitor({"R00": 800, "R04": 200, "R40": 800, "R44": 200})
    new = m.proposal(ROUND_ROBIN, 2)
    assert new is not None and new["R00"] != new["R40"]
    # Balanced (1.0 s each) and slightly uneven loads: no move.
    assert m.proposal({"R00": 0, "R04": 0, "R40": 1, "R44": 1}, 2) is None
    slight = _monitor({"R00": 550, "R04": 500, "R40": 500, "R44": 450})
    assert slight.proposal(ROUND_ROBIN, 2) is None  # 1.05 s -> 1.0 s is not a fifth
    # Too few visits to trust, or one worker: nothing proposed.
    assert _monitor({"R00": 800, "R04": 200, "R40": 800, "R44": 200}, n=2).proposal(
        ROUND_ROBIN, 2) is None
    assert m.proposal(dict.fromkeys(ROUND_ROBIN, 0), 1) is None


def test_the_promise_names_the_worker_that_cannot_finish_in_time() -> None:
    m = _monitor({"R00": 1200, "R04": 300, "R40": 1100, "R44": 300})
    problem, need = m.promise(ROUND_ROBIN, {0: 2, 1: 2}, 2.0)
    assert need == pytest.approx(2.3)
    assert problem is not None and problem.reason == "visit_timeout"
    assert "worker 0 (R00+R40)" in problem.message and "2.30 s" in problem.message
    # Within the timeout: no problem, and the predicted time is the busier worker's.
    ok, need = m.promise(ROUND_ROBIN, {0: 2, 1: 2}, 2.5)
    assert ok is None and need == pytest.approx(2.3)
    # A backlog of two more jobs on worker 1 (0.3 s each) makes it the one that is late.
    light = _monitor({"R00": 500, "R04": 500, "R40": 500, "R44": 500})
    problem, need = light.promise(ROUND_ROBIN, {0: 2, 1: 6}, 2.0)
    assert need == pytest.approx(1.0 + 4 * 0.5)
    assert problem is not None and "worker 1 (R04+R44)" in problem.message
    # Before every corner has a measured cost nothing is promised either way.
    assert math.isnan(_monitor({"R00": 500}).promise(ROUND_ROBIN, {}, 2.0)[1])


def test_cache_report_sums_workers_and_counts_builds_after_warm_up() -> None:
    m = WorkloadMonitor()
    m.record_warm(11, {"map": (0, 18, 18, 82)})
    m.record_warm(12, {"map": (0, 18, 18, 82)})
    m.record("R00", 100.0, 11, {"map": (40, 18, 18, 82)})
    m.record("R04", 100.0, 12, {"map": (38, 20, 20, 82)})
    (key, value), = m.cache_values()
    assert key == "cache.map"
    # Since the warm-up: 78 hits and 2 builds (20 - 18 on worker 12): 78 / 80 = 97.5 %.
    assert value.startswith("hit 97.5 % after warm-up (78 hits, 2 builds; 36 built at warm-up)")
    assert "held 38 in 2 worker(s), size 82 each" in value


def test_warmed_tiles_serve_every_field_in_them_from_the_first() -> None:
    """After warming the tiles of a small field patch, pair geometries at new fields in it
    build no tile and trace no field directly (a cold process traces a tile's first two
    fields); an estimate then does not depend on what the process estimated before."""
    inst = load_instrument("lsst")
    algo = load_algorithm("lsq")
    wl = inst.wavelength_nm("r", None)
    reset_caches()
    try:
        # A patch inside one 0.125 deg tile per side, near the R00 half-chips.
        fi, fe = (-1.2549, -1.1903), (-1.1903, -1.1903)
        assert mp.tile_of(fi, 0.125) == (-11, -10) and mp.tile_of(fe, 0.125) == (-10, -10)
        mid = (0.5 * (fi[0] + fe[0]), 0.5 * (fi[1] + fe[1]))
        built = warm_star_fields(inst, "r", wl, algo, {"intra": [fi], "extra": [fe]}, [mid])
        # One map and one pupil tile per side, one design tile.
        assert built == 5
        before = {k: (s.builds, s.direct) for k, s in mp.field_tile_stats().items()}
        rng = np.random.default_rng(3)
        for _ in range(2):
            di, de = rng.uniform(-0.01, 0.01, 2), rng.uniform(-0.01, 0.01, 2)
            pair_geometry(inst, "r", wl, (fi[0] + di[0], fi[1] + di[1]),
                          (fe[0] + de[0], fe[1] + de[1]), inst.defocal_offset_mm, algo)
        after = {k: (s.builds, s.direct) for k, s in mp.field_tile_stats().items()}
        assert after == before
        stats = mp.field_tile_stats()
        assert stats["map"].hits >= 4 and stats["map"].held == 2
        assert stats["map"].size >= 64
    finally:
        reset_caches()
