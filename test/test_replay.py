"""Record a simulated closed-loop run, replay it offline, and get the live results back.

The graph runs in this process as ``cwfs-ros bringup --sim`` would (camera_sim_node +
wavefront_node + ofc_node via :func:`cwfs_ros.ros.launch.run_nodes`, on the test's own Context and
DDS domain), with the bag recorder (:class:`cwfs_ros.ros.bag.Recorder`) on the same executor. Two
visits are triggered; an independent tester node keeps every CornerWavefront and
DofCorrection it receives over DDS. After the graph is shut down, :func:`cwfs_ros.cli.replay.replay`
re-runs the estimator and the OFC solver on the bag with no middleware, and its CSV files must
hold the very numbers the live nodes published. They are computed by the same float64 code
(worker processes and replay both pin BLAS to one thread), so the tolerance is 1e-6 nm for the
Zernikes and 1e-9 (relative) for the DoF.
"""

from __future__ import annotations

import csv
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from recorded_graph import record_visits, start_graph

pytestmark = pytest.mark.ros

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("cwfs_ros.sim")


from cwfs_ros.cli import replay as R  # noqa: E402
from cwfs_ros.cli.main import main as cli_main  # noqa: E402
from cwfs_ros.layout import CORNERS  # noqa: E402
from cwfs_ros.ros import bag as B  # noqa: E402
from cwfs_ros.ros.common import stamp_to_ns  # noqa: E402
from cwfs_ros.runtime.visits import format_stamp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
VISITS = 2
OVERLAY = {
    "wavefront_node": {"ros__parameters": {"visit_timeout_s": 10.0}},
    # the simulated camera renders a visit per trigger, faster than the survey's cadence
    # (min_visit_period_s 15 s): the readout's 2 s, as config/sim.yaml sets it
    "ofc_node": {"ros__parameters": {"kp": 0.6, "ki": 0.0, "min_visit_period_s": 2.0}},
    "camera_sim_node": {"ros__parameters": {
        "visit_period_s": 0.0, "n_photons": 2e5, "perturbation_seed": 11,
        "perturbation_scale": 1.0, "render_seed": 5}},
}
# Topics the nodes create for their own plumbing, not part of the data flow.
PLUMBING = {"/rosout", "/parameter_events"}


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory, ros_domain_module):
    """Run the simulated graph for two visits, recording everything; returns what it saw."""
    tmp = tmp_path_factory.mktemp("replay")
    overlay = tmp / "overlay.yaml"
    overlay.write_text(yaml.safe_dump(OVERLAY))
    bag_dir = tmp / "run_bag"
    ctx = rclpy.Context()
    th, started = start_graph(ctx, ros_domain_module, overlay)
    out: dict = {"overlay": overlay, "bag": bag_dir, "tmp": tmp}
    try:
        nodes = started["nodes"]
        out.update(record_visits(ctx, started, bag_dir, VISITS, tester="replay_tester",
                                 dof_timeout_s=90))
        out["published"] = {
            n.get_name(): dict(n.get_publisher_names_and_types_by_node(n.get_name(),
                                                                       n.get_namespace()))
            for n in nodes.values()}
        out["params"] = {name: {p: nodes[name].get_parameter(p).value
                                for p in nodes[name]._parameters}
                         for name in ("wavefront_node", "ofc_node")}
    finally:
        ctx.try_shutdown()
        th.join(15)
    return out


def _estimate_next_to_the_corners() -> None:
    """Build pair geometries at two fields next to each corner's, in this process: the
    field tiles then serve the corners' own fields (a tile's third field on), which the
    live workers, fresh processes, traced directly.  The replay must start from a fresh
    worker's state (core.estimator.reset_caches), whatever ran before it in its process;
    without that it was 0.075 nm off the live estimates after test_blur had run."""
    from cwfs_ros.runtime.visits import load_corner_fields
    from cwfs_ros.wfs import load_instrument
    from cwfs_ros.wfs.estimator import load_algorithm, pair_geometry

    inst = load_instrument("lsst")
    algo = load_algorithm("lsq")
    for f in load_corner_fields().values():
        for k in (1, 2):
            near = {s: (f[s][0] + 1e-3 * k, f[s][1]) for s in ("intra", "extra")}
            pair_geometry(inst, "r", inst.wavelength_nm("r", None), near["intra"],
                          near["extra"], inst.defocal_offset_mm, algo)


@pytest.fixture(scope="module")
def replayed(recorded_run):
    _estimate_next_to_the_corners()
    t0 = time.monotonic()
    res = R.replay(recorded_run["bag"], recorded_run["tmp"] / "replay_out",
                   params_files=[recorded_run["overlay"]], progress=False)
    print(f"\nreplay of {VISITS} visits took {time.monotonic() - t0:.1f} s")
    return res


def test_default_topics_are_everything_the_graph_publishes(recorded_run):
    published = {}
    for topics in recorded_run["published"].values():
        for name, types in topics.items():
            if name not in PLUMBING:
                published[name] = types
    assert set(published) == set(B.DEFAULT_TOPICS)
    for name, types in published.items():
        assert types == [B.DEFAULT_TOPICS[name]], name


def test_recording_holds_the_run(recorded_run):
    s = recorded_run["summary"]
    counts = {t: n for t, (_, n, _) in s.topics.items()}
    for c in CORNERS:
        for side in ("intra", "extra"):
            assert counts[f"/aos/wfs/{c}/{side}/image"] == VISITS
        assert counts[f"/aos/wfs/{c}/wavefront"] == VISITS
    assert counts["/aos/wfs/wavefront"] == VISITS
    assert counts["/aos/ofc/dof_correction"] == VISITS
    assert counts["/aos/sim/truth"] == VISITS
    with B.open_bag(recorded_run["bag"]) as bag:
        assert bag.storage == "mcap" and bag.version == 9
        assert {t: i.count for t, i in bag.topics.items()} == counts
        # the live corner results in the bag are bit-identical to what the tester received
        stored = {(m.corner, stamp_to_ns(m.header.stamp)): list(m.zernikes_nm)
                  for _, m in bag.decoded([f"/aos/wfs/{c}/wavefront" for c in CORNERS])}
    live = {(m.corner, stamp_to_ns(m.header.stamp)): list(m.zernikes_nm)
            for m in recorded_run["live_corners"]}
    assert stored == live


def test_replay_parameters_are_the_nodes(recorded_run):
    """replay resolves the same parameter values the running nodes had (YAML files)."""
    for node in ("wavefront_node", "ofc_node"):
        mine = R.node_parameters(node, [recorded_run["overlay"]])
        live = recorded_run["params"][node]
        assert ({"solver", "seeing_fwhm_arcsec", "sensors.R00.intra.rot90"}
                if node == "wavefront_node" else {"kp", "dof_mask"}) <= set(mine)
        for name in mine:
            a, b = mine[name], live[name]
            if isinstance(b, (list, tuple)) or hasattr(b, "tolist"):
                a, b = list(a), list(b)
            assert a == b and type(a) is type(b) or (isinstance(a, float) and a == b), \
                (node, name, a, b)


def test_replay_reproduces_the_live_corner_wavefronts(recorded_run, replayed):
    live = recorded_run["live_corners"]
    assert len(live) == VISITS * len(CORNERS)
    assert all(m.valid for m in live), [m.status for m in live if not m.valid]
    with open(replayed.files["zernikes"], newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == VISITS * len(CORNERS)
    by_key = {(r["corner"], r["stamp"]): r for r in rows}
    worst = 0.0
    for m in live:
        r = by_key[(m.corner, format_stamp(stamp_to_ns(m.header.stamp)))]
        assert r["valid"] == "1", r["status"]
        assert list(m.noll) == list(range(4, 23))
        z = np.array([float(r[f"Z{j}"]) for j in range(4, 23)])
        diff = np.abs(z - np.asarray(m.zernikes_nm))
        worst = max(worst, float(diff.max()))
        assert diff.max() <= 1e-6, (m.corner, diff.max())
    # the visits are numbered in stamp order, each with its four corners
    stamps = sorted({stamp_to_ns(m.header.stamp) for m in live})
    for r in rows:
        assert int(r["visit"]) == 1 + [format_stamp(s) for s in stamps].index(r["stamp"])
    print(f"max |Z replay - Z live| = {worst:.3g} nm")


def test_replay_reproduces_the_live_dof_corrections(recorded_run, replayed):
    live = recorded_run["live_dofs"]
    assert len(live) == VISITS and all(m.valid for m in live), [m.status for m in live]
    with open(replayed.files["dof"], newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == VISITS
    names = [h[len("dof."):] for h in rows[0] if h.startswith("dof.")]
    assert len(names) == 50 and names[0] == "M2_dz"
    by_stamp = {r["stamp"]: r for r in rows}
    for m in live:
        r = by_stamp[format_stamp(stamp_to_ns(m.header.stamp))]
        assert r["valid"] == "1", r["status"]
        dof = np.array([float(r[f"dof.{n}"]) for n in names])
        total = np.array([float(r[f"total.{n}"]) for n in names])
        np.testing.assert_allclose(dof, np.asarray(m.dof), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(total, np.asarray(m.dof_total), rtol=1e-9, atol=1e-12)
        assert float(r["wavefront_rms_nm"]) == pytest.approx(m.wavefront_rms_nm, rel=1e-9)
        assert int(r["n_modes_used"]) == m.n_modes_used
    # a non-trivial correction: the perturbed telescope was actually being corrected
    assert np.abs(np.asarray(live[0].dof[:10])).max() > 1e-3


def test_replay_reports_the_comparison_and_writes_plots(replayed):
    cmp = replayed.comparison
    assert cmp is not None
    assert cmp.corners_compared == VISITS * len(CORNERS) and cmp.dof_compared == VISITS
    assert cmp.corners_validity_mismatch == 0 and cmp.dof_validity_mismatch == 0
    assert cmp.max_zernike_diff_nm <= 1e-6
    assert cmp.max_dof_diff <= 1e-9 and cmp.max_dof_total_diff <= 1e-9
    assert cmp.corners_not_live == 0 and cmp.live_corners_not_replayed == 0
    import matplotlib.image as mpimg

    for key in ("zernikes_plot", "dof_plot"):
        img = mpimg.imread(replayed.files[key])
        assert img.shape[0] > 400 and img.shape[1] > 800
        assert np.std(img[..., :3]) > 0.05  # not a blank canvas


def test_replay_cli_matches_even_with_more_blas_threads(recorded_run, tmp_path):
    """The command line, in a fresh process whose environment asks for two BLAS/OpenMP
    threads: replay still pins one (the workers do), else the sums run in another order and
    the estimates differ from the live ones by ~1e-4 nm."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS="2", OMP_NUM_THREADS="2",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    argv = ["replay", str(recorded_run["bag"]), "--out", str(tmp_path / "o"), "--params",
            str(recorded_run["overlay"]), "--no-progress", "--no-plots"]
    # offline: the middleware is never loaded
    code = ("import sys; from cwfs_ros.cli.main import main; rc = main(sys.argv[1:]); "
            "assert 'rclpy' not in sys.modules, 'replay loaded rclpy'; sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True,
                          timeout=120, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr
    assert f"{VISITS * 4} corner estimates ({VISITS * 4} valid)" in proc.stdout
    assert "live comparison: 8 corner estimates, max |dZ| = 0 nm" in proc.stdout
    cmp = json.loads((tmp_path / "o" / "summary.json").read_text())["comparison"]
    assert cmp["max_zernike_diff_nm"] <= 1e-6 and cmp["max_dof_diff"] <= 1e-9
    assert (tmp_path / "o" / "zernikes.csv").is_file()
    assert not (tmp_path / "o" / "zernikes.png").exists()


def test_replay_of_a_bag_without_images_is_a_clean_error(tmp_path, capsys):
    src = Path(__file__).parent / "data" / "rosbag2-real" / "mcap-cdr_test"
    # An earlier ROS test's rclpy Future that failed at its teardown ("exception was never
    # retrieved") prints to stderr when the garbage collector frees it, which once landed
    # in this test's capture: collect it first, and not during the call whose stderr is
    # checked line for line.
    gc.collect()
    capsys.readouterr()
    gc.disable()
    try:
        code = cli_main(["replay", str(src), "--out", str(tmp_path / "o"), "--no-progress"])
    finally:
        gc.enable()
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("cwfs-ros replay: error:") and "no image topics" in err
    assert len(err.splitlines()) == 1


def test_replay_layers_sim_yaml_for_a_simulated_run(recorded_run, replayed, tmp_path):
    """The bag holds /aos/sim/truth, so config/sim.yaml sits under the --params files (as
    bringup --sim does); the test overlay sets kp/ki itself, so the values are the overlay's."""
    assert any("sim.yaml applied" in n for n in replayed.comparison.notes)
    assert replayed.ofc_params["kp"] == OVERLAY["ofc_node"]["ros__parameters"]["kp"]
    # Without any overlay, the simulated run's gains come from config/sim.yaml ...
    import yaml as _yaml

    from cwfs_ros.ros.launch import sim_params_file

    sim_kp = _yaml.safe_load(sim_params_file().read_text())["ofc_node"]["ros__parameters"]["kp"]
    auto = R.replay(recorded_run["bag"], tmp_path / "auto", progress=False, plots=False)
    assert auto.ofc_params["kp"] == sim_kp
    # ... and --sim no gives config/params.yaml's (ts_ofc's) gains.
    plain = R.replay(recorded_run["bag"], tmp_path / "plain", progress=False, plots=False,
                     sim=False)
    assert plain.ofc_params["kp"] != sim_kp
    assert not any("sim.yaml applied" in n for n in plain.comparison.notes)


def _renamed_bag(src: Path, dst: Path, rename: dict, rotate: str | None = None) -> None:
    """A copy of ``src`` with topics renamed (as a camera driver names them), and the
    images of topic ``rotate`` turned a quarter counter-clockwise (a camera mounted so)."""
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer

    store = B.cwfs_typestore()
    with Reader(src) as reader:
        writer = Writer(dst, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        conns = {}
        for c in reader.connections:
            conns[c.id] = writer.add_connection(
                rename.get(c.topic, c.topic), c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest,
                serialization_format="cdr",
                offered_qos_profiles=c.ext.offered_qos_profiles)
        for c, t, data in reader.messages():
            if c.topic == rotate:
                msg = store.deserialize_cdr(data, c.msgtype)
                assert msg.encoding == "32FC1" and msg.height == msg.width
                img = np.frombuffer(msg.data.tobytes(), "<f4").reshape(msg.height, msg.width)
                msg.data = np.frombuffer(np.rot90(img, 1).astype("<f4").tobytes(), np.uint8)
                data = store.serialize_cdr(msg, c.msgtype)
            writer.write(conns[c.id], t, data)
        writer.close()


def test_replay_remaps_a_camera_drivers_topics_and_orients_its_stamps(recorded_run, tmp_path,
                                                                      capsys):
    """A bag whose image topics carry a camera driver's names, one camera turned a quarter:
    `--remap` and `-p sensors.R00.intra.rot90:=3` give the live estimates back; without
    them, replay says what it lacks."""
    rename = {f"/aos/wfs/{c}/{s}/image": f"/cam/{c.lower()}_{s}/image_raw"
              for c in CORNERS for s in ("intra", "extra")}
    bag = tmp_path / "driver_bag"
    _renamed_bag(recorded_run["bag"], bag, rename, rotate="/aos/wfs/R00/intra/image")
    base = ["replay", str(bag), "--params", str(recorded_run["overlay"]), "--no-progress",
            "--no-plots"]
    capsys.readouterr()
    assert cli_main([*base, "--out", str(tmp_path / "none")]) == 2
    assert "no image topics" in capsys.readouterr().err
    remaps = [a for src, dst in rename.items() for a in ("--remap", f"{dst}:={src}")]
    assert cli_main([*base, "--out", str(tmp_path / "o"), *remaps,
                     "-p", "sensors.R00.intra.rot90:=3"]) == 0
    with open(tmp_path / "o" / "zernikes.csv", newline="") as f:
        rows = {(r["corner"], r["stamp"]): r for r in csv.DictReader(f)}
    assert len(rows) == len(recorded_run["live_corners"]) == VISITS * 4
    for live in recorded_run["live_corners"]:
        row = rows[(live.corner, format_stamp(stamp_to_ns(live.header.stamp)))]
        got = [float(row[f"Z{j}"]) for j in range(4, 23)]
        np.testing.assert_allclose(got, live.zernikes_nm, atol=1e-6)
    # The turned camera without its orientation: R00's estimate is not the live one.
    assert cli_main([*base, "--out", str(tmp_path / "u"), *remaps]) == 0
    with open(tmp_path / "u" / "zernikes.csv", newline="") as f:
        r00 = [r for r in csv.DictReader(f) if r["corner"] == "R00"]
    live00 = [m for m in recorded_run["live_corners"] if m.corner == "R00"]
    assert any(r["valid"] != "1" or max(
        abs(float(r[f"Z{j}"]) - m.zernikes_nm[j - 4]) for j in range(4, 23)) > 1.0
        for r in r00 for m in live00 if r["stamp"] == format_stamp(stamp_to_ns(m.header.stamp)))
    # A bad rule or a misspelt parameter: said, nothing run.
    capsys.readouterr()
    assert cli_main([*base, "--out", str(tmp_path / "x"), "--remap", "/nope:=/x"]) == 2
    assert "the bag has no topic /nope" in capsys.readouterr().err
    assert cli_main([*base, "--out", str(tmp_path / "x"), *remaps,
                     "-p", "sensors.R00.intra.rot:=3"]) == 2
    assert "did you mean 'sensors.R00.intra.rot90'?" in capsys.readouterr().err


def test_replay_summary_names_each_refused_correction_and_why(tmp_path):
    from cwfs_ros.cli.replay import DofRow, ReplayResult

    def row(visit: int, valid: bool, status: str) -> DofRow:
        return DofRow(visit, visit * 10**9, valid, status, 1.0, 0.5, 10, False, [0.0] * 50,
                      [0.0] * 50)

    dofs = [row(1, False, "no_rotator_angle: no camera rotator angle received yet"),
            row(2, True, "ok")] + [row(k, False, f"corner_invalid: case {k}")
                                   for k in range(3, 10)]
    text = ReplayResult(tmp_path / "bag", tmp_path, 72, [], dofs, None, {}, {}, {}).format()
    assert "9 DoF corrections (1 valid)" in text
    assert ("correction of visit 1 refused: no_rotator_angle: no camera rotator angle "
            "received yet") in text
    assert "correction of visit 2 refused" not in text
    assert "correction of visit 6 refused: corner_invalid: case 6" in text
    assert "correction of visit 7 refused" not in text and "... and 3 more refused" in text
