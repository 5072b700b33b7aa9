"""A simulated closed-loop graph in this process, recorded to a bag while visits are triggered.

Shared by the replay tests (test_replay.py, test_replay_frames.py): the graph of
``cwfs-ros bringup --sim`` (:func:`cwfs_ros.ros.launch.run_nodes` on the test's own Context and
DDS domain) with the bag recorder and an independent tester node on the same executor.
"""

from __future__ import annotations

import threading
from pathlib import Path

import rclpy
from conftest import wait_for
from cwfs_msgs.msg import CornerWavefront, DofCorrection
from std_srvs.srv import Trigger

from cwfs_ros.layout import CORNERS
from cwfs_ros.ros import bag as B
from cwfs_ros.ros.common import OUTPUT_QOS
from cwfs_ros.ros.launch import run_nodes

GRAPH = ["wavefront_node", "ofc_node", "camera_sim_node"]


def start_graph(ctx, domain: int, overlay: Path) -> tuple[threading.Thread, dict]:
    """Start the simulated graph in a thread; its nodes by name and its executor."""
    started, ready = {}, threading.Event()

    def on_ready(nodes, executor):
        started["nodes"] = {n.get_name(): n for n in nodes}
        started["executor"] = executor
        ready.set()

    th = threading.Thread(target=run_nodes, args=(GRAPH,),
                          kwargs={"context": ctx, "domain_id": domain,
                                  "params_files": [overlay], "on_ready": on_ready},
                          daemon=True)
    th.start()
    if not ready.wait(30):
        ctx.try_shutdown()
        th.join(15)
        raise AssertionError("nodes did not start")
    return th, started


def record_visits(ctx, started: dict, bag_dir: Path, visits: int, *, tester: str,
                  dof_timeout_s: float, warm_up_timeout_s: float = 60.0) -> dict:
    """Trigger ``visits`` visits one at a time while recording; what the bag summary and an
    independent tester node got (every CornerWavefront and DofCorrection).

    ``warm_up_timeout_s`` bounds the wait for the workers' warm-up: the stamp path takes a
    few seconds, the field tiles of four frame corners ~30 s on an idle 2-core machine and
    more than twice that on a loaded one."""
    nodes = started["nodes"]
    wf, cam = nodes["wavefront_node"], nodes["camera_sim_node"]
    rec = B.Recorder(bag_dir, context=ctx, storage="mcap")
    node = rclpy.create_node(tester, context=ctx)
    corners: list[CornerWavefront] = []
    dofs: list[DofCorrection] = []
    for c in CORNERS:
        node.create_subscription(CornerWavefront, f"aos/wfs/{c}/wavefront", corners.append,
                                 OUTPUT_QOS)
    node.create_subscription(DofCorrection, "aos/ofc/dof_correction", dofs.append, OUTPUT_QOS)
    trigger = node.create_client(Trigger, "camera_sim_node/trigger")
    started["executor"].add_node(rec.node)
    started["executor"].add_node(node)
    assert trigger.wait_for_service(timeout_sec=10)
    wait_for(lambda: wf.ready, warm_up_timeout_s, "wavefront worker warm-up")
    wait_for(lambda: all(s.get_publisher_count() > 0 for s in rec.subscriptions.values()),
             15, "the recorder to match every publisher of the graph")
    wait_for(lambda: all(p.get_subscription_count() >= 2 for p in cam.pubs.values()), 10,
             "the images to have two readers (wavefront_node, recorder)")
    for k in range(1, visits + 1):
        applied = cam.stats["corrections_applied"]
        fut = trigger.call_async(Trigger.Request())
        wait_for(fut.done, 10, "trigger response")
        assert fut.result().success, fut.result().message
        wait_for(lambda k=k: len(dofs) >= k, dof_timeout_s, f"DofCorrection of visit {k}")
        wait_for(lambda a=applied: cam.stats["corrections_applied"] > a, 10,
                 f"correction {k} applied")
    # Everything the tester got must be in the bag too before it is closed.
    wait_for(lambda: rec.counts()["/aos/ofc/dof_correction"] >= visits
             and all(rec.counts()[f"/aos/wfs/{c}/wavefront"] >= visits for c in CORNERS),
             10, "the recorder to get the last results")
    return {"summary": rec.close(), "live_corners": list(corners), "live_dofs": list(dofs)}
