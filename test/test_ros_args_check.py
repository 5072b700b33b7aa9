"""`--ros-args -p NAME:=VALUE` is held to the declared parameters, as parameter files are;
`bringup --sim` keeps DDS discovery to this host unless `--visible`."""

from __future__ import annotations

import argparse
import os

import pytest

from cwfs_ros.ros import launch as L
from cwfs_ros.ros.params import check_overrides

OFC = {"kp": "double", "dry_run": "bool", "band": "string", "dof_mask": "bool_array",
       "seeing_fwhm_arcsec": "double"}
WF = {"solver": "string", "workers": "integer", "seeing_fwhm_arcsec": "double"}


def test_a_misspelt_override_is_named_with_its_close_match():
    problems = check_overrides(["--ros-args", "-p", "dryrun:=true"], {"ofc_node": OFC})
    assert len(problems) == 1
    assert "dryrun" in problems[0] and "declares no such parameter" in problems[0]
    assert "did you mean 'dry_run'?" in problems[0]
    # Nothing close: no guess.
    assert "did you mean" not in check_overrides(["-p", "zzz:=1"], {"ofc_node": OFC})[0]


def test_override_types_follow_the_declaration():
    assert check_overrides(["-p", "kp:=0.3", "--param", "dry_run:=true", "-p", "band:=g",
                            "-p", "dof_mask:=[true, false]"], {"ofc_node": OFC}) == []
    (p,) = check_overrides(["-p", "kp:=fast"], {"ofc_node": OFC})
    assert "ofc_node.kp is a double" in p and "'fast' is a string" in p
    # rcl reads an exponent without a dot, or unsigned, as a double; YAML 1.1 as text.
    assert check_overrides(["-p", "kp:=1e-3", "-p", "seeing_fwhm_arcsec:=1.0e0"],
                           {"ofc_node": OFC}) == []


def test_an_override_reaches_every_node_and_must_be_declared_by_one():
    nodes = {"ofc_node": OFC, "wavefront_node": WF}
    assert check_overrides(["-p", "seeing_fwhm_arcsec:=0.7", "-p", "kp:=0.2",
                            "-p", "solver:=lsq"], nodes) == []
    (p,) = check_overrides(["-p", "solvr:=lsq"], nodes)
    assert "did you mean 'solver'?" in p
    # A node prefix limits it to that node.
    (p,) = check_overrides(["-p", "ofc_node:solver:=lsq"], nodes)
    assert "ofc_node declares no such parameter" in p
    (p,) = check_overrides(["-p", "camera_sim_node:kp:=0.2"], nodes)
    assert "no node camera_sim_node here" in p
    # Remappings and other rcl arguments are not parameters.
    assert check_overrides(["-r", "__node:=x", "--log-level", "warn"], nodes) == []


@pytest.mark.ros
def test_a_misspelt_override_stops_the_node_before_it_runs(ros_domain, capsys):
    import rclpy

    code = L.run_nodes(["ofc_node"], ros_args=["-p", "dryrun:=true"], context=rclpy.Context(),
                       domain_id=ros_domain, on_ready=lambda *a: pytest.fail("started"))
    err = capsys.readouterr().err
    assert code == 2 and "did you mean 'dry_run'?" in err and "not running" in err, err


@pytest.mark.ros
def test_the_node_command_refuses_a_misspelt_dry_run(ros_domain, capsys, monkeypatch):
    """The command a user types: it used to start live (dry_run False)."""
    from cwfs_ros import cli

    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    code = cli.main(["node", "ofc_node", "--ros-args", "-p", "dryrun:=true"])
    err = capsys.readouterr().err
    assert code == 2 and "dryrun" in err and "did you mean 'dry_run'?" in err, err


@pytest.mark.ros
def test_a_good_override_starts_the_node_with_it(ros_domain):
    import rclpy

    ctx = rclpy.Context()
    seen = {}

    def on_ready(nodes, _executor):
        seen.update(dry_run=nodes[0].get_parameter("dry_run").value)
        ctx.try_shutdown()  # spin returns at once

    code = L.run_nodes(["ofc_node"], ros_args=["-p", "dry_run:=true"], context=ctx,
                       domain_id=ros_domain, on_ready=on_ready)
    assert code == 0 and seen == {"dry_run": True}


def _bringup(monkeypatch, *argv: str) -> str | None:
    seen = {}

    def fake_run_nodes(names, **kw):
        seen["range"] = os.environ.get(L.DISCOVERY_ENV)
        return 0

    monkeypatch.setattr(L, "run_nodes", fake_run_nodes)
    ap = argparse.ArgumentParser()
    L.add_bringup_parser(ap.add_subparsers(dest="command"))
    a = ap.parse_args(["bringup", *argv])
    assert a.func(a) == 0
    return seen["range"]


def test_bringup_sim_is_kept_to_this_host_unless_visible(monkeypatch, capsys):
    monkeypatch.delenv(L.DISCOVERY_ENV, raising=False)
    assert _bringup(monkeypatch, "--sim") == "LOCALHOST"
    assert "limited to this host" in capsys.readouterr().err
    monkeypatch.delenv(L.DISCOVERY_ENV, raising=False)
    assert _bringup(monkeypatch, "--sim", "--visible") is None
    # The real loop (no --sim) follows the environment.
    monkeypatch.setenv(L.DISCOVERY_ENV, "SUBNET")
    assert _bringup(monkeypatch) == "SUBNET"


def test_ros_arguments_before_ros_args_are_refused_with_where_they_go(capsys):
    from cwfs_ros.cli.main import main

    assert main(["bringup", "-p", "kp:=0.2"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("cwfs-ros bringup: error: unrecognized arguments: -p kp:=0.2; ROS "
                           "arguments go after --ros-args: cwfs-ros bringup --ros-args -p "
                           "kp:=0.2"), err
    # A command that runs no node gets the plain usage error.
    assert main(["validate", "-p", "kp:=0.2"]) == 2
    err = capsys.readouterr().err
    assert "unrecognized arguments: -p kp:=0.2" in err and "--ros-args" not in err, err
