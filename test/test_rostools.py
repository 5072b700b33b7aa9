"""The ros2-shaped tools (`cwfs-ros topic|param|node list`) against a live graph.

A real ofc_node (and a plain publisher for the echo/hz cases) runs in this process on the
test's own DDS domain; each tool is run through the real command line (``cli.main``), which
starts its own rclpy context on ``ROS_DOMAIN_ID`` and discovers the node over DDS.
"""

from __future__ import annotations

import re

import pytest
import yaml
from conftest import REPO_ROOT, spin_thread

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")

from cwfs_ros import cli  # noqa: E402
from cwfs_ros.ros.params import check_declared, flatten  # noqa: E402


def _params_yaml(node: str) -> dict:
    raw = yaml.safe_load((REPO_ROOT / "config" / "params.yaml").read_text())
    return flatten(raw[node]["ros__parameters"])


@pytest.fixture
def graph(ros_domain, monkeypatch):
    """An ofc_node and a publisher node spinning on the test's domain; the tools' domain."""
    from rclpy.executors import MultiThreadedExecutor

    from cwfs_ros.ros.ofc_node import OfcNode

    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    ofc = OfcNode(context=ctx)
    pub = rclpy.create_node("test_publisher", context=ctx)
    ex = MultiThreadedExecutor(num_threads=2, context=ctx)
    ex.add_node(ofc)
    ex.add_node(pub)
    th = spin_thread(ex)
    th.start()
    try:
        yield ofc, pub
    finally:
        ctx.try_shutdown()
        th.join(5)
        ex.shutdown(timeout_sec=1.0)


def _run(capsys, *argv: str) -> tuple[int, str, str]:
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_node_list_shows_the_running_nodes_and_hides_its_own(graph, capsys):
    code, out, _ = _run(capsys, "node", "list")
    assert code == 0
    assert {"/ofc_node", "/test_publisher"} <= set(out.split()), out
    assert not any(n.startswith("/_") for n in out.split()), out
    code, out, _ = _run(capsys, "node", "list", "-a")
    assert code == 0 and any(n.startswith("/_cwfs_ros_cli_") for n in out.split()), out


def test_topic_list_with_types(graph, capsys):
    code, out, _ = _run(capsys, "topic", "list", "-t")
    assert code == 0
    lines = out.splitlines()
    assert "/aos/wfs/wavefront [cwfs_msgs/msg/WavefrontVector]" in lines, out
    assert "/aos/ofc/dof_correction [cwfs_msgs/msg/DofCorrection]" in lines, out
    code, out, _ = _run(capsys, "topic", "list")
    assert code == 0 and "/aos/wfs/wavefront" in out.splitlines()


def test_param_get_prints_the_value_as_ros2_does(graph, capsys):
    want = _params_yaml("ofc_node")
    code, out, _ = _run(capsys, "param", "get", "ofc_node", "kp")
    assert (code, out) == (0, f"Double value is: {want['kp']}\n")
    code, out, _ = _run(capsys, "param", "get", "/ofc_node", "dry_run")
    assert (code, out) == (0, f"Boolean value is: {want['dry_run']}\n")
    code, out, _ = _run(capsys, "param", "get", "ofc_node", "band", "--hide-type")
    assert (code, out) == (0, f"{want['band']}\n")
    code, out, err = _run(capsys, "param", "get", "ofc_node", "no_such_param")
    assert code == 1 and "not set" in err and out == ""
    code, out, err = _run(capsys, "param", "get", "ofc_node", "dryrun")
    assert code == 1 and "did you mean 'dry_run'?" in err, err


def test_param_list_names_every_declared_parameter(graph, capsys):
    ofc, _ = graph
    code, out, _ = _run(capsys, "param", "list", "ofc_node")
    assert code == 0
    assert out.splitlines() == [f"  {n}" for n in sorted(ofc._parameters)]
    code, out, _ = _run(capsys, "param", "list", "ofc_node", "--param-type")
    assert "  kp (type: double)" in out.splitlines()
    assert "  dof_mask (type: boolean array)" in out.splitlines()


def test_param_set_changes_the_running_node_or_says_why_not(graph, capsys):
    ofc, _ = graph
    code, out, _ = _run(capsys, "param", "set", "ofc_node", "kp", "0.25")
    assert (code, out) == (0, "Set parameter successful\n")
    assert ofc.get_parameter("kp").value == 0.25
    code, out, _ = _run(capsys, "param", "set", "ofc_node", "dry_run", "true")
    assert code == 0 and ofc.get_parameter("dry_run").value is True
    # An integer for a double is refused by the node (as rclpy does), and said.
    code, out, err = _run(capsys, "param", "set", "ofc_node", "kp", "1")
    assert code == 1 and out == "" and "Set parameter failed" in err, err
    assert ofc.get_parameter("kp").value == 0.25
    # Exponents YAML 1.1 reads as text are doubles, as rcl reads them in a file or -p.
    code, out, _ = _run(capsys, "param", "set", "ofc_node", "kp", "2e-1")
    assert code == 0 and ofc.get_parameter("kp").value == 0.2
    code, out, _ = _run(capsys, "param", "set", "ofc_node", "kp", "3.0e-1")
    assert code == 0 and ofc.get_parameter("kp").value == 0.3
    # A negative value with an exponent is a value, not an option, with or without "--".
    code, out, err = _run(capsys, "param", "set", "ofc_node", "rotator_angle_deg", "-1.5e1")
    assert code == 0, err
    assert ofc.get_parameter("rotator_angle_deg").value == -15.0
    code, out, err = _run(capsys, "param", "set", "ofc_node", "rotator_angle_deg", "--",
                          "-2.5e1")
    assert code == 0 and ofc.get_parameter("rotator_angle_deg").value == -25.0, err
    # Text YAML cannot read is the text itself, as ros2 takes it; a YAML mapping is no
    # parameter value and is said so in one line; an integer for a double names the fix.
    code, out, err = _run(capsys, "param", "set", "ofc_node", "frame_id", "a\tb")
    assert code == 1 and "control characters" in err and "Traceback" not in err, err
    code, out, err = _run(capsys, "param", "set", "ofc_node", "frame_id", "x: y")
    assert code == 1 and "is a YAML mapping" in err and "Traceback" not in err, err
    code, out, err = _run(capsys, "param", "set", "ofc_node", "rotator_angle_deg", "-5")
    assert code == 1 and "(a double is written with a point: -5.0)" in err, err
    # A misspelt name: named, with the nearest declared one.
    code, out, err = _run(capsys, "param", "set", "ofc_node", "dryrun", "true")
    assert code == 1 and "declares no parameter 'dryrun'; did you mean 'dry_run'?" in err, err


def test_param_dump_is_a_parameter_file_of_the_live_values(graph, capsys, tmp_path):
    from cwfs_ros.ros.launch import declared_kinds

    ofc, _ = graph
    code, out, _ = _run(capsys, "param", "dump", "ofc_node")
    assert code == 0
    dumped = yaml.safe_load(out)
    assert list(dumped) == ["/ofc_node"]
    live = {n: ofc.get_parameter(n).value for n in ofc._parameters}
    live = {n: list(v) if isinstance(v, (list, tuple)) or hasattr(v, "tolist") else v
            for n, v in live.items()}
    assert flatten(dumped["/ofc_node"]["ros__parameters"]) == live
    # ... and loads back as a --params file: every name declared, every type right.
    f = tmp_path / "dump.yaml"
    f.write_text(out)
    assert check_declared([f], "ofc_node", declared_kinds(ofc)) == []


def test_tools_say_when_the_node_or_topic_is_not_there(graph, capsys):
    code, out, err = _run(capsys, "param", "dump", "no_node", "--timeout", "0.5")
    assert code == 1 and "node /no_node not found" in err and out == ""
    code, out, err = _run(capsys, "topic", "echo", "/no/topic", "--once", "--timeout", "0.5")
    assert code == 1 and "topic /no/topic not found" in err and out == ""


def test_echo_says_when_no_message_comes_in_time(graph, capsys):
    from std_msgs.msg import String

    _, pub = graph
    pub.create_publisher(String, "/test/silent", 10)  # there, but never publishes
    code, out, err = _run(capsys, "topic", "echo", "/test/silent", "--once", "--wait", "1")
    assert code == 1 and out == "" and "/test/silent: 0 of 1 message(s) within 1 s" in err


def _publish_periodically(node, msg_type, topic, make, period_s=0.1):
    pub = node.create_publisher(msg_type, topic, 10)
    n = [0]

    def tick():
        n[0] += 1
        pub.publish(make(n[0]))

    return node.create_timer(period_s, tick)


def test_topic_echo_prints_messages_as_yaml(graph, capsys):
    from cwfs_msgs.msg import CornerWavefront

    _, pub = graph

    def make(k):
        m = CornerWavefront(corner="R44", solver="lsq", valid=True, status="ok",
                            iterations=k, n_pairs=1)
        m.field_deg = [1.19, 1.22]
        m.noll = list(range(4, 23))
        m.zernikes_nm = [float(j) * 10.0 for j in range(4, 23)]
        return m

    _publish_periodically(pub, CornerWavefront, "/aos/wfs/R44/wavefront", make)
    code, out, _ = _run(capsys, "topic", "echo", "/aos/wfs/R44/wavefront", "--once")
    assert code == 0 and out.endswith("---\n") and out.count("---\n") == 1
    doc = yaml.safe_load(out[:-len("---\n")])
    assert list(doc)[:3] == ["header", "corner", "field_deg"]  # the message's field order
    assert doc["corner"] == "R44" and doc["solver"] == "lsq" and doc["valid"] is True
    assert doc["noll"] == list(range(4, 23))
    assert doc["zernikes_nm"] == [float(j) * 10.0 for j in range(4, 23)]
    assert doc["field_deg"] == [1.19, 1.22]
    code, out, _ = _run(capsys, "topic", "echo", "/aos/wfs/R44/wavefront", "-n", "3",
                        "--field", "iterations")
    counts = [int(x) for x in out.split("---\n") if x.strip()]
    assert code == 0 and len(counts) == 3 and counts == sorted(counts), out


def test_topic_echo_cuts_long_arrays_as_ros2_does(graph, capsys):
    from sensor_msgs.msg import Image

    _, pub = graph

    def make(_k):
        return Image(height=10, width=20, encoding="mono8", step=20, data=bytes(range(200)))

    _publish_periodically(pub, Image, "/test/image", make)
    code, out, _ = _run(capsys, "topic", "echo", "/test/image", "--once")
    data = yaml.safe_load(out.split("---\n")[0])["data"]
    assert code == 0 and data == [*range(128), "..."]
    code, out, _ = _run(capsys, "topic", "echo", "/test/image", "--once", "--full-length")
    assert yaml.safe_load(out.split("---\n")[0])["data"] == list(range(200))
    code, out, _ = _run(capsys, "topic", "echo", "/test/image", "--once", "--no-arr")
    assert "length: 200" in yaml.safe_load(out.split("---\n")[0])["data"]


def test_topic_hz_prints_ros2s_report(graph, capsys):
    from std_msgs.msg import String

    _, pub = graph
    _publish_periodically(pub, String, "/test/chatter", lambda k: String(data=str(k)))
    code, out, _ = _run(capsys, "topic", "hz", "/test/chatter", "-n", "2")
    assert code == 0
    reports = re.findall(r"average rate: (\d+\.\d{3})\n\tmin: (\d+\.\d{3})s max: "
                         r"(\d+\.\d{3})s std dev: (\d+\.\d{5})s window: (\d+)\n", out)
    assert len(reports) == 2, out
    windows = [int(r[4]) for r in reports]
    assert windows[0] >= 2 and windows[1] > windows[0]
    for rate, lo, hi, _std, _w in reports:
        assert float(rate) > 0 and float(lo) <= float(hi)


def test_hz_report_arithmetic():
    from cwfs_ros.ros.tools import hz_report

    # Deltas 0.1, 0.3 s: mean 0.2 s (5 Hz), std 0.1 s, window 3 messages.
    text = hz_report([0, 100_000_000, 400_000_000])
    assert text == ("average rate: 5.000\n\tmin: 0.100s max: 0.300s std dev: 0.10000s "
                    "window: 3")
    assert hz_report([5]) is None


def test_tools_see_a_graph_kept_to_this_host(ros_domain, monkeypatch, capsys):
    """bringup --sim's isolation (discovery LOCALHOST) keeps the tools on this host able to
    inspect it: a node started so is listed by a tool with the default range."""
    from rclpy.executors import SingleThreadedExecutor

    from cwfs_ros.ros.launch import DISCOVERY_ENV, SIM_DISCOVERY_RANGE

    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    monkeypatch.setenv(DISCOVERY_ENV, SIM_DISCOVERY_RANGE)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)  # the range is read here
    monkeypatch.delenv(DISCOVERY_ENV)
    node = rclpy.create_node("sim_graph_node", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    th = spin_thread(ex)
    th.start()
    try:
        code, out, _ = _run(capsys, "node", "list")
    finally:
        ctx.try_shutdown()
        th.join(5)
    assert code == 0 and "/sim_graph_node" in out.split(), out
