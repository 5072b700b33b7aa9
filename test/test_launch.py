"""The launcher (cwfs_ros.ros.launch): parameter layering, --ros-args, FastDDS profile, CLIs."""

from __future__ import annotations

import argparse
import os

import pytest

from cwfs_ros.ros import launch as L


def test_ros_arguments_layer_defaults_user_files_and_ros_args(tmp_path):
    user = tmp_path / "mine.yaml"
    user.write_text("ofc_node:\n  ros__parameters:\n    kp: 0.25\n")
    args = L.ros_arguments([user], ["-p", "kp:=0.3"])
    assert args == ["--ros-args", "--params-file", str(L.default_params_file()),
                    "--params-file", str(user), "--ros-args", "-p", "kp:=0.3"]
    assert L.ros_arguments([], ["--ros-args", "--log-level", "debug"])[-3:] == [
        "--ros-args", "--log-level", "debug"]
    assert L.ros_arguments(defaults=False) == []
    with pytest.raises(L.LaunchError, match="not found"):
        L.ros_arguments([tmp_path / "missing.yaml"])


def test_params_yaml_overlay_and_ros_args_reach_the_node(tmp_path, ros_domain):
    rclpy = pytest.importorskip("rclpy")
    from cwfs_ros.ros.ofc_node import OfcNode

    user = tmp_path / "mine.yaml"
    user.write_text("ofc_node:\n  ros__parameters:\n    kp: 0.25\n    ki: 0.05\n"
                    "    dry_run: true\n")
    ctx = rclpy.Context()
    rclpy.init(args=["x", *L.ros_arguments([user], ["-p", "ki:=0.01"])], context=ctx,
               domain_id=ros_domain)
    try:
        node = OfcNode(context=ctx)
        p = {n: node.get_parameter(n).value for n in ("kp", "ki", "dry_run", "matrix_source",
                                                       "band")}
        node.destroy_node()
    finally:
        ctx.try_shutdown()
    # default file (matrix_source, band) < user file (kp, dry_run) < --ros-args -p (ki)
    assert p == {"kp": 0.25, "ki": 0.01, "dry_run": True, "matrix_source": "bundled",
                 "band": "r"}


def test_default_params_file_declares_what_the_nodes_declare():
    yaml = pytest.importorskip("yaml")
    raw = yaml.safe_load(L.default_params_file().read_text())
    assert set(raw) == {"wavefront_node", "ofc_node", "camera_sim_node"}
    assert raw["wavefront_node"]["ros__parameters"]["corners"] == ["R00", "R04", "R40", "R44"]
    assert raw["ofc_node"]["ros__parameters"]["matrix_source"] == "bundled"


def test_nodes_without_a_params_file_start_with_its_values(ros_context):
    """A node built with no parameter file (a test, an embedding program) declares the
    values of config/params.yaml, read here from the file itself: wavefront_node used to
    declare solver exp beside the file's lsq.  Every declared name is in the file."""
    pytest.importorskip("rclpy")
    yaml = pytest.importorskip("yaml")
    from rclpy.parameter import Parameter

    from cwfs_ros.ros.camera_sim_node import CameraSimNode
    from cwfs_ros.ros.ofc_node import OfcNode
    from cwfs_ros.ros.params import flatten
    from cwfs_ros.ros.wavefront_node import WavefrontNode

    raw = yaml.safe_load(L.default_params_file().read_text())
    # workers 1 and one corner: a light pool; both are compared as overridden.
    small = {"workers": 1, "corners": ["R00"]}
    for key, cls, over in (("ofc_node", OfcNode, {}), ("camera_sim_node", CameraSimNode, {}),
                           ("wavefront_node", WavefrontNode, small)):
        node = cls(context=ros_context,
                   parameter_overrides=[Parameter(k, value=v) for k, v in over.items()])
        try:
            names = [n for n in node._parameters
                     if n not in ("use_sim_time", "start_type_description_service")]
            got = {n: node.get_parameter(n).value for n in names}
            ranged = {n: (bool(d.floating_point_range), bool(d.integer_range))
                      for n, d in zip(names, node.describe_parameters(names), strict=True)}
        finally:
            node.destroy_node()
        want = {**flatten(raw[key]["ros__parameters"]), **over}
        assert got == want, key
        # The declared type follows the descriptor's range (a float range: a float, even
        # where the file writes an integer), so a later set of either kind is accepted.
        for n, (fp, integer) in ranged.items():
            if fp:
                assert type(got[n]) is float, (key, n, got[n])
            if integer:
                assert type(got[n]) is int, (key, n, got[n])
        assert any(fp for fp, _ in ranged.values()) and any(i for _, i in ranged.values())
    assert raw["wavefront_node"]["ros__parameters"]["solver"] == "lsq"


def test_bundled_defaults_are_typed_by_the_descriptor_and_checked(monkeypatch):
    """An integer in the file for a floating-point parameter is declared as a float; a
    string where a number is needed (YAML reads 1e6 as one), a float for an integer, or a
    name the file lacks is a ConfigError naming the file and the key."""
    pytest.importorskip("rclpy")
    from cwfs_ros.errors import ConfigError
    from cwfs_ros.ros import common

    monkeypatch.setattr(common, "_bundled_params", lambda path: {
        "x_node": {"rate": 5, "big": "1e6", "count": 2.5, "flag": True, "n": 3}})
    declared: dict = {}

    class Recorder:
        def declare_parameter(self, name, value, descriptor):
            declared[name] = value

    d = common.bundled_declarer(Recorder(), "x_node")
    d("rate", common.describe("a rate", fp_range=(0.0, 10.0)))
    d("n", common.describe("a count", int_range=(0, 9)))
    d("flag", common.describe("a switch"))
    assert declared == {"rate": 5.0, "n": 3, "flag": True}
    assert type(declared["rate"]) is float
    for name, desc in (("big", common.describe("b", fp_range=(0.0, 1e9))),
                       ("count", common.describe("c", int_range=(0, 9))),
                       ("flag", common.describe("f", fp_range=(0.0, 1.0))),
                       ("missing", common.describe("m"))):
        with pytest.raises(ConfigError, match=rf"params\.yaml: x_node\.{name}"):
            d(name, desc)


def test_fastdds_profile_is_set_unless_already_set(monkeypatch):
    from cwfs_ros.ros import dds

    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE", raising=False)
    path = dds.ensure_fastdds_profile()
    assert path and path.endswith("config/fastdds_profile.xml") and os.path.isfile(path)
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == path
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", "/somewhere/else.xml")
    assert dds.ensure_fastdds_profile() == "/somewhere/else.xml"


def test_subcommand_parsers():
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="command", required=True)
    L.add_bringup_parser(sub)
    L.add_node_parser(sub)
    a = ap.parse_args(["bringup", "--sim", "--params", "a.yaml", "--params", "b.yaml",
                       "--ros-args", "-p", "band:=g", "-r", "__ns:=/x"])
    assert a.sim and a.params == ["a.yaml", "b.yaml"] and a.func is L.cmd_bringup
    assert a.ros_args == ["-p", "band:=g", "-r", "__ns:=/x"]
    a = ap.parse_args(["node", "ofc_node", "--ros-args", "-p", "dry_run:=true"])
    assert a.name == "ofc_node" and not hasattr(a, "sim") and a.func is L.cmd_node
    assert a.ros_args == ["-p", "dry_run:=true"]
    assert ap.parse_args(["bringup"]).ros_args == []
    with pytest.raises(SystemExit):
        ap.parse_args(["node", "no_such_node"])


def test_node_classes_load_lazily():
    assert L.load_node_class("ofc_node").__name__ == "OfcNode"
    assert L.load_node_class("wavefront_node").__name__ == "WavefrontNode"
    assert L.load_node_class("camera_sim_node").__name__ == "CameraSimNode"
    with pytest.raises(L.LaunchError, match="unknown node"):
        L.load_node_class("foo_node")


def test_bringup_sim_loads_sim_yaml_before_the_users_files(monkeypatch):
    seen = {}
    monkeypatch.setattr(L, "run_nodes", lambda names, **kw: seen.update(names=names, **kw) or 0)
    ap = argparse.ArgumentParser()
    L.add_bringup_parser(ap.add_subparsers(dest="command"))
    a = ap.parse_args(["bringup", "--sim", "--params", "u.yaml"])
    assert a.func(a) == 0
    assert seen["names"] == ["wavefront_node", "ofc_node", "camera_sim_node"]
    assert seen["params_files"] == [L.sim_params_file(), "u.yaml"]
    seen.clear()
    a = ap.parse_args(["bringup"])
    a.func(a)
    assert seen["params_files"] == [] and "camera_sim_node" not in seen["names"]


def test_sim_yaml_only_sets_parameters_the_nodes_declare():
    """A misspelt key would be ignored silently by rcl; params.yaml lists every parameter."""
    yaml = pytest.importorskip("yaml")
    declared = yaml.safe_load(L.default_params_file().read_text())
    sim = yaml.safe_load(L.sim_params_file().read_text())
    assert sim, "config/sim.yaml is empty"
    for node, body in sim.items():
        assert node in declared
        unknown = set(body["ros__parameters"]) - set(declared[node]["ros__parameters"])
        assert not unknown, f"{node}: {unknown}"


@pytest.mark.ros
@pytest.mark.parametrize("text, words", [
    ("ofc_node:\n  ros__parameters:\n    kp: [1, 2\n", "not valid YAML"),
    ("ofc_node: 3\n", "has no ros__parameters mapping"),
    # rcl would silently keep params.yaml's kp under a value of another type ...
    ("ofc_node:\n  ros__parameters:\n    kp: fast\n",
     "'fast' is a string, the parameter is a double"),
    # ... and silently ignore a name no node declares: the controller would stay live.
    ("ofc_node:\n  ros__parameters:\n    dryrun: true\n", "declares no such parameter"),
])
def test_bad_parameter_files_stop_the_launch_with_the_reason(tmp_path, ros_domain, capsys,
                                                             text, words):
    import rclpy

    f = tmp_path / "user.yaml"
    f.write_text(text)
    code = L.run_nodes(["ofc_node"], params_files=[f], context=rclpy.Context(),
                       domain_id=ros_domain, on_ready=lambda *a: pytest.fail("started"))
    err = capsys.readouterr().err
    assert code == 2 and words in err and str(f) in err, err


@pytest.mark.ros
def test_shipped_parameter_files_pass_the_check(ros_domain):
    """params.yaml and sim.yaml only set declared parameters, with the declared types."""
    import rclpy

    from cwfs_ros.ros.params import check_declared

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    try:
        from cwfs_ros.ros.ofc_node import OfcNode

        node = OfcNode(context=ctx)
        kinds = L.declared_kinds(node)
        assert kinds["kp"] == "double" and kinds["dry_run"] == "bool"
        assert kinds["dof_mask"] == "bool_array"
        assert check_declared([L.default_params_file(), L.sim_params_file()], "ofc_node",
                              kinds) == []
        node.destroy_node()
    finally:
        ctx.try_shutdown()


def test_the_controller_accepts_every_pair_count_the_selection_can_claim():
    """ofc_node refuses a corner claiming more donut pairs than its max_pairs
    (implausible_uncertainty); the shipped selection must never claim more, or every frames
    corner with that many pairs would be refused."""
    yaml = pytest.importorskip("yaml")
    from cwfs_ros.frames.selection import load_selection_config

    params = yaml.safe_load(L.default_params_file().read_text())
    assert (params["ofc_node"]["ros__parameters"]["max_pairs"]
            >= load_selection_config().max_pairs)
