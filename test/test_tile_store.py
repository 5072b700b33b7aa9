"""Field tiles kept on disk (cwfs_ros.wfs.tile_store): a process that reads a tile from the
store gets the tile a process that traces it builds, to the last bit, and a damaged store
costs a rebuild, never a wrong tile or a crash."""

from __future__ import annotations

import numpy as np
import pytest

from cwfs_ros.wfs import mapping as mp
from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry, reset_caches, warm_star_fields
from cwfs_ros.wfs.instrument import load_instrument
from cwfs_ros.wfs.tile_store import use_tile_store

# A patch inside one 0.125 deg tile per side, near the R00 half-chips (as test_workload).
FI, FE = (-1.2549, -1.1903), (-1.1903, -1.1903)
MID = (0.5 * (FI[0] + FE[0]), 0.5 * (FI[1] + FE[1]))
STARS = ((FI[0] + 0.004, FI[1] - 0.007), (FE[0] - 0.006, FE[1] + 0.003))


def _warm_and_read() -> tuple[dict, dict, object]:
    """Warm the patch's tiles in a fresh process state; (counts made per kind, read from the
    store per kind, the geometry of a pair at new star fields in the patch)."""
    inst = load_instrument("lsst")
    algo = load_algorithm("lsq")
    wl = inst.wavelength_nm("r", None)
    reset_caches()
    warm_star_fields(inst, "r", wl, algo, {"intra": [FI], "extra": [FE]}, [MID])
    stats = mp.field_tile_stats()
    geom = pair_geometry(inst, "r", wl, *STARS, inst.defocal_offset_mm, algo)
    return ({k: s.builds for k, s in stats.items()}, {k: s.loaded for k, s in stats.items()},
            geom)


def _same_geometry(a, b) -> None:
    for name in ("mask_intra", "mask_extra", "weight", "intrinsic_nm"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for side in ("mapping_intra", "mapping_extra"):
        for f in ("x_px", "y_px", "jxx", "jxy", "jyx", "jyy", "transmitted"):
            np.testing.assert_array_equal(getattr(getattr(a, side), f),
                                          getattr(getattr(b, side), f), err_msg=f"{side}.{f}")
    # The solvers answer alike: the same estimate from the same difference image.
    d = np.random.default_rng(0).normal(size=a.region.size)
    np.testing.assert_array_equal(a.solver.solve(d, a.kappa), b.solver.solve(d, b.kappa))


@pytest.fixture
def store(tmp_path):
    root = tmp_path / "tiles"
    yield root
    mp.use_field_tile_store(None)
    reset_caches()


def test_a_tile_read_from_the_store_is_the_tile_built(store):
    mp.use_field_tile_store(None)
    _, _, traced = _warm_and_read()  # no store: every tile traced
    mp.use_field_tile_store(store)
    made, loaded, first = _warm_and_read()  # an empty store: traced, then stored
    # One map and one pupil tile per side, one design tile; none of them read.
    assert made == {"map": 2, "pupil": 2, "design": 1} and sum(loaded.values()) == 0
    files = sorted(p.parent.name for p in store.rglob("*.npz"))
    assert files == ["design", "map", "map", "pupil", "pupil"]
    builds = mp.map_tile_builds, mp.design_tile_builds
    made, loaded, second = _warm_and_read()  # as a new process: every tile read
    assert loaded == {"map": 2, "pupil": 2, "design": 1}
    assert (mp.map_tile_builds, mp.design_tile_builds) == builds  # nothing traced
    _same_geometry(first, traced)
    _same_geometry(second, traced)


def test_a_damaged_or_foreign_store_is_rebuilt_not_trusted(store):
    mp.use_field_tile_store(store)
    _, _, good = _warm_and_read()
    files = sorted(store.rglob("*.npz"))
    files[0].write_bytes(files[0].read_bytes()[:100])  # truncated
    with np.load(files[1]) as z:  # a NaN where a number belongs
        arrays = {k: z[k].copy() for k in z.files}
    key = next(k for k, v in arrays.items() if v.dtype.kind == "f" and v.size > 1)
    arrays[key].flat[0] = np.nan
    np.savez(files[1], **arrays)
    files[2].write_text("not a tile")
    s = mp.use_field_tile_store(store)  # as a new process
    _, loaded, again = _warm_and_read()
    assert sum(loaded.values()) == len(files) - 3  # the three damaged ones rebuilt
    assert s.rejected == 3, s.problems
    said = "\n".join(s.problems)
    assert "unreadable" in said and "content is damaged" in said, said
    assert s.report().startswith("3 stored tiles rejected and rebuilt"), s.report()
    _same_geometry(again, good)
    _, loaded, _ = _warm_and_read()  # and stored anew
    assert sum(loaded.values()) == len(files)
    # Another salt (other code or library versions) reads nothing written before.
    use_tile_store(store, "another build")
    reset_caches()
    inst = load_instrument("lsst")
    algo = load_algorithm("lsq")
    warm_star_fields(inst, "r", inst.wavelength_nm("r", None), algo,
                     {"intra": [FI], "extra": [FE]}, [MID])
    assert sum(s.loaded for s in mp.field_tile_stats().values()) == 0


def test_a_tile_stored_under_another_tiles_name_is_rejected_and_said(store):
    s = mp.use_field_tile_store(store)
    _, _, good = _warm_and_read()
    one, other = sorted((s.dir / "map").glob("*.npz"))  # the two sides' map tiles
    other.write_bytes(one.read_bytes())  # a whole, valid tile of the other side
    s = mp.use_field_tile_store(store)  # as a new process
    _, loaded, again = _warm_and_read()
    assert loaded == {"map": 1, "pupil": 2, "design": 1}
    assert s.rejected == 1 and "another tile" in s.report(), s.report()
    _same_geometry(again, good)  # the other side's tile was not used
    s = mp.use_field_tile_store(store)
    _, loaded, _ = _warm_and_read()  # and the right one stored in its place
    assert loaded == {"map": 2, "pupil": 2, "design": 1} and s.rejected == 0


def test_an_unwritable_store_costs_the_build_only(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    try:
        s = mp.use_field_tile_store(blocker / "tiles")  # no directory can be made here
        made, loaded, _ = _warm_and_read()
        assert sum(made.values()) == 5 and sum(loaded.values()) == 0
        assert s.writes == 0 and s.write_errors
        assert "5 failed writes" in s.report() and "cannot write" in s.report(), s.report()
        # Its reads are misses, not rejected tiles, and the unusable root is said once.
        assert s.rejected == 0 and "0 stored tiles rejected" in s.report(), s.report()
        assert sum("cannot write or read tiles" in p for p in s.problems) == 1, s.problems
    finally:
        mp.use_field_tile_store(None)
        reset_caches()


def test_the_tiles_of_other_versions_go_after_a_month_unused(tmp_path):
    import os
    import time

    month_ago = time.time() - 31 * 86400

    def salt_dir(name: str, age_s: float | None = None):
        d = tmp_path / name
        (d / "map").mkdir(parents=True)
        (d / "map" / "t.npz").write_bytes(b"x")
        (d / ".last_used").touch()
        if age_s is not None:
            for p in (d / ".last_used", d / "map" / "t.npz", d / "map", d):
                os.utime(p, (age_s, age_s))
        return d

    old, recent = salt_dir("0123456789abcdef", month_ago), salt_dir("fedcba9876543210")
    # Old but written to today (a long-lived process of that version): kept.
    busy = salt_dir("00000000000000aa", month_ago)
    (busy / "map" / "new.npz").write_bytes(b"y")
    # Not the store's: a salt-like name without its mark, one with a foreign file, and
    # another project's directory, all a month old: never removed.
    unmarked = salt_dir("00000000000000bb", month_ago)
    (unmarked / ".last_used").unlink()
    foreign = salt_dir("00000000000000cc", month_ago)
    (foreign / "notes.txt").write_text("mine")
    os.utime(foreign / "notes.txt", (month_ago, month_ago))
    victim = tmp_path / "old_project"
    (victim / "data").mkdir(parents=True)
    (victim / "data" / "today.txt").write_text("kept")
    for p in (victim / "data", victim):
        os.utime(p, (month_ago, month_ago))
    try:
        s = mp.use_field_tile_store(tmp_path)
        assert not old.exists() and recent.exists() and s.dir.is_dir()
        assert (s.dir / ".last_used").exists()
        assert busy.exists() and (unmarked / "map" / "t.npz").exists()
        assert (foreign / "notes.txt").exists() and (victim / "data" / "today.txt").exists()
    finally:
        mp.use_field_tile_store(None)


def test_pruning_follows_no_link_swapped_in_after_its_scan(tmp_path, monkeypatch):
    """Another process that can write in the store root swaps an old salt directory for a
    link to someone's data between the scan and the removal: nothing behind the link goes;
    a directory whose mark is a link is not the store's."""
    import os
    import time

    from cwfs_ros.wfs import tile_store as ts

    root, victim = tmp_path / "tiles", tmp_path / "victim"
    (victim / "k").mkdir(parents=True)
    (victim / "k" / "results.npz").write_text("precious")
    month_ago = time.time() - 90 * 86400
    old = root / "abcdefabcdefabcd"
    (old / "k").mkdir(parents=True)
    (old / ".last_used").touch()
    (old / "k" / "results.npz").write_text("x")
    linked = root / "0000000000000011"
    (linked / "map").mkdir(parents=True)
    (linked / ".last_used").symlink_to(victim / "k" / "results.npz")
    for p in (old / ".last_used", old / "k" / "results.npz"):
        os.utime(p, (month_ago, month_ago))
    real = ts._remove_salt_dir

    def swapped_first(d, files):
        os.rename(d, root / "moved")
        os.symlink(victim, d)
        return real(d, files)

    monkeypatch.setattr(ts, "_remove_salt_dir", swapped_first)
    assert ts.TileStore(root, "salt").prune() == []
    assert (victim / "k" / "results.npz").read_text() == "precious"
    assert linked.is_dir() and (linked / ".last_used").is_symlink()


def test_a_fifo_or_a_huge_file_in_the_store_is_refused_without_blocking(store):
    import os
    import threading

    s = mp.use_field_tile_store(store)
    _warm_and_read()
    pupil, other = sorted((s.dir / "pupil").glob("*.npz"))
    pupil.unlink()
    os.mkfifo(pupil)  # a read would wait for a writer for ever
    with open(other, "r+b") as f:
        f.truncate(300 * 2**20)  # sparse: bigger than any tile
    s = mp.use_field_tile_store(store)
    done = threading.Event()
    result = {}

    def warm():
        result["loaded"] = _warm_and_read()[1]
        done.set()

    threading.Thread(target=warm, daemon=True).start()
    assert done.wait(120), "the warm-up blocked on a FIFO in the tile store"
    assert result["loaded"] == {"map": 2, "pupil": 0, "design": 1}
    said = " | ".join(s.problems)
    assert s.rejected == 2 and "not a regular file" in said and "more than a tile" in said, said
