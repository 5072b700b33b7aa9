"""Who may change a parameter, over DDS: the safety guards are read-only (set at start only),
and every other runtime change is logged and reported on /diagnostics with its old and new
value.

The nodes run in this process on the test's domain; the changes are made by the project's own
``cwfs-ros param set`` in a process of its own, as an operator (or anyone else on the domain)
would make them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from conftest import REPO_ROOT, quiet_ofc_node, wait_for

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy")

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: E402

from cwfs_ros.ros.wavefront_node import WavefrontNode  # noqa: E402

# What an outside process tried to switch the guards off with (docs/reliability.md).
GUARDS = [
    ("ofc_node", "controller", "pid"),
    ("ofc_node", "max_step_scale", "0.0"),
    ("ofc_node", "plausibility_margin_nm", "1000000.0"),
    ("ofc_node", "plausibility_n_sigma", "100.0"),
    ("ofc_node", "allow_partial", "true"),
    ("ofc_node", "refuse_repeats", "false"),
    ("ofc_node", "min_visit_period_s", "0.0"),
    ("ofc_node", "max_future_s", "0.0"),
    ("ofc_node", "max_abs_zernike_nm", "0.0"),
    ("ofc_node", "clip_to_range", "false"),
    ("ofc_node", "max_condition", "1000000000000.0"),
    ("ofc_node", "max_inconsistency", "1000000.0"),
    ("ofc_node", "min_corner_rms_nm", "0.0"),
    ("ofc_node", "matrix_source", "ts_ofc"),
    ("ofc_node", "measurement_model", "estimator"),
    ("ofc_node", "rotator_angle_source", "topic"),
    ("ofc_node", "vector_publishers", "0"),
    ("wavefront_node", "pairing_tolerance_s", "0.5"),
    ("wavefront_node", "max_pending_mb", "65536.0"),
    ("wavefront_node", "max_future_s", "0.0"),
]


def _param_set(domain: int, node: str, name: str, value: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               PYTHONPATH=str(REPO_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run([sys.executable, "-m", "cwfs_ros.cli", "param", "set", node, name,
                           value], env=env, cwd=REPO_ROOT, capture_output=True, text=True,
                          timeout=120)


def _param_set_many(domain: int, node: str, pairs: list[tuple[str, str]]
                    ) -> dict[str, tuple[int, str]]:
    """``cwfs-ros param set NODE NAME VALUE`` for each pair, in one process of its own (the
    tool's ``cli.main`` per pair): name -> (exit status, what it wrote to stderr)."""
    code = (
        "import contextlib, io, json, sys\nfrom cwfs_ros import cli\nout = {}\n"
        "for name, value in zip(sys.argv[2::2], sys.argv[3::2]):\n"
        "    err = io.StringIO()\n"
        "    with contextlib.redirect_stderr(err):\n"
        "        rc = cli.main(['param', 'set', sys.argv[1], name, value])\n"
        "    out[name] = (rc, err.getvalue())\n"
        "print('@@' + json.dumps(out))\n")
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
               PYTHONPATH=str(REPO_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    argv = [sys.executable, "-c", code, node] + [x for p in pairs for x in p]
    r = subprocess.run(argv, env=env, cwd=REPO_ROOT, capture_output=True, text=True,
                       timeout=300)
    line = [x for x in r.stdout.splitlines() if x.startswith("@@")]
    assert line, (r.stdout, r.stderr)
    return {k: tuple(v) for k, v in json.loads(line[-1][2:]).items()}


@pytest.fixture
def nodes(ros_context, spin):
    """ofc_node (active, no rotator) and an unconfigured wavefront_node (its parameters and
    services, no workers), with an observer of /diagnostics."""
    ofc = spin(quiet_ofc_node(ros_context))
    wf = spin(WavefrontNode(context=ros_context, autostart=False))
    obs = spin(rclpy.create_node("observer", context=ros_context))
    diag: list[DiagnosticArray] = []
    obs.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 50)
    return ofc, wf, diag


def _ofc_status(diag: list[DiagnosticArray], *words: str) -> DiagnosticStatus | None:
    for arr in reversed(list(diag)):
        for st in arr.status:
            if st.name.startswith("ofc_node") and all(w in st.message for w in words):
                return st
    return None


def test_guards_cannot_be_switched_off_at_runtime(nodes, ros_domain):
    ofc, wf, _ = nodes
    before = {(n, p): (ofc if n == "ofc_node" else wf).get_parameter(p).value
              for n, p, _ in GUARDS}
    out = {}
    for node in ("ofc_node", "wavefront_node"):
        got = _param_set_many(ros_domain, node, [(p, v) for n, p, v in GUARDS if n == node])
        out.update({(node, k): v for k, v in got.items()})
    for n, p, v in GUARDS:
        rc, text = out[(n, p)]
        assert rc == 1 and "read-only" in text, (n, p, v, rc, text)
        now = (ofc if n == "ofc_node" else wf).get_parameter(p).value
        assert now == before[(n, p)], (n, p, now)
    assert type(ofc.solver).__name__ == "KalmanOFC" and not ofc.solver.allow_partial


def test_an_operators_change_is_logged_and_reported(nodes, ros_domain):
    ofc, _, diag = nodes
    r = _param_set(ros_domain, "ofc_node", "kp", "0.3")
    assert r.returncode == 0 and "Set parameter successful" in r.stdout, r.stderr
    assert ofc.get_parameter("kp").value == 0.3
    wait_for(lambda: _ofc_status(diag, "kp", "0.18 -> 0.3") is not None, 10,
             "the change of kp on /diagnostics")
    st = _ofc_status(diag, "kp", "0.18 -> 0.3")
    assert st.level == DiagnosticStatus.WARN
    kv = {x.key: x.value for x in st.values}
    assert kv["parameter_changes"] == "1" and "kp" in kv["last_parameter_change"]
    # A DoF masked live (a hexapod axis taken out of the loop): the entry that changed.
    mask = ["true"] * 50
    mask[5] = "false"
    r = _param_set(ros_domain, "ofc_node", "dof_mask", "[" + ", ".join(mask) + "]")
    assert r.returncode == 0, r.stderr
    wait_for(lambda: _ofc_status(diag, "dof_mask", "[5] True->False") is not None, 10,
             "the change of dof_mask on /diagnostics")
    assert not ofc.solver.dof_mask[5]
