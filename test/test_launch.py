"""The launcher (cwfs_ros.launch): parameter layering, --ros-args, FastDDS profile, CLI parsers."""

from __future__ import annotations

import argparse
import os

import pytest

from cwfs_ros import launch as L


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
    from cwfs_ros.nodes.ofc_node import OfcNode

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


def test_fastdds_profile_is_set_unless_already_set(monkeypatch):
    monkeypatch.delenv(L.PROFILE_ENV, raising=False)
    path = L.ensure_fastdds_profile()
    assert path and path.endswith("config/fastdds_profile.xml") and os.path.isfile(path)
    monkeypatch.setenv(L.PROFILE_ENV, "/somewhere/else.xml")
    assert L.ensure_fastdds_profile() == "/somewhere/else.xml"


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
