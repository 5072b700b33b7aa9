"""Tests of the cwfs_msgs interfaces as built by tools/bootstrap.sh (msg_defs/).

They check the message layout contract (fixed array lengths), that rclpy
enforces it when field checks are on, CDR round trips, a real DDS pub/sub, and
that `rosbags` computes the same type hashes and CDR bytes as rosidl, so that
bags written by either side stay readable by the other.
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

MSG_NAMES = ["CornerWavefront", "WavefrontVector", "DofCorrection", "SimTruth"]

# The layout contract: every fixed-size array field and its length.
FIXED_ARRAYS = {
    "CornerWavefront": {"field_deg": 2, "field_intra_deg": 2, "field_extra_deg": 2},
    "WavefrontVector": {"zernikes_nm": 76, "corner_valid": 4, "corners": 4,
                        "uncertainty_nm": 76, "n_pairs": 4},
    "DofCorrection": {"dof": 50, "dof_total": 50, "dof_uncertainty": 50},
    "SimTruth": {"dof_state": 50, "zernikes_nm": 76, "intrinsic_nm": 76},
}

_ARRAY_TYPE = re.compile(r"^(?P<base>.+)\[(?P<n>\d+)\]$")


def _msg_class(name):
    import cwfs_msgs.msg

    return getattr(cwfs_msgs.msg, name)


def _cwfs_msgs_prefix() -> Path:
    """Install prefix of cwfs_msgs (the venv, or a colcon install space)."""
    import cwfs_msgs

    # <prefix>/lib/pythonX.Y/site-packages/cwfs_msgs/__init__.py
    return Path(cwfs_msgs.__file__).resolve().parents[4]


def _fill_value(base: str, n: int):
    return {"double": [0.5] * n, "boolean": [True] * n, "string": ["x"] * n,
            "uint16": [3] * n}[base]


def test_messages_import_with_expected_fields():
    for name in MSG_NAMES:
        cls = _msg_class(name)
        types = cls.get_fields_and_field_types()
        assert types["header"] == "std_msgs/Header", name
        fixed = {
            field: int(m["n"])
            for field, t in types.items()
            if (m := _ARRAY_TYPE.match(t)) is not None
        }
        assert fixed == FIXED_ARRAYS[name], name
        msg = cls()
        for field, n in fixed.items():
            assert len(getattr(msg, field)) == n, (name, field)

    cw = _msg_class("CornerWavefront").get_fields_and_field_types()
    assert cw["noll"] == "sequence<uint8>"
    assert cw["zernikes_nm"] == "sequence<double>"
    assert cw["uncertainty_nm"] == "sequence<double>"
    assert cw["compute_ms"] == "float"
    assert cw["n_pairs"] == "uint16"


@pytest.mark.parametrize(
    "name,field,n",
    [(name, field, n) for name, fields in FIXED_ARRAYS.items() for field, n in fields.items()],
)
def test_fixed_array_length_enforced(name, field, n):
    cls = _msg_class(name)
    base = _ARRAY_TYPE.match(cls.get_fields_and_field_types()[field])["base"]
    msg = cls(check_fields=True)
    setattr(msg, field, _fill_value(base, n))  # the right length is accepted
    assert len(getattr(msg, field)) == n
    for wrong in (n - 1, n + 1):
        with pytest.raises(AssertionError):
            setattr(msg, field, _fill_value(base, wrong))


def test_check_fields_env_var_enforces_lengths():
    """ROS_PYTHON_CHECK_FIELDS=1 (as `make test` sets it) turns the checks on globally."""
    code = (
        "from cwfs_msgs.msg import DofCorrection, WavefrontVector\n"
        "for cls, field, n in [(DofCorrection, 'dof', 49), (WavefrontVector, 'zernikes_nm', 75)]:\n"
        "    try:\n"
        "        setattr(cls(), field, [0.0] * n)\n"
        "    except AssertionError:\n"
        "        continue\n"
        "    raise SystemExit(f'{cls.__name__}.{field} accepted {n} values')\n"
        "print('checked')\n"
    )
    env = dict(os.environ, ROS_PYTHON_CHECK_FIELDS="1")
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.strip() == "checked"


def _sample_dof_correction():
    msg = _msg_class("DofCorrection")()
    msg.header.stamp.sec = 1_700_000_123
    msg.header.stamp.nanosec = 456_789
    msg.header.frame_id = "telescope"
    msg.dof = np.linspace(-25.0, 25.0, 50)
    msg.dof_total = np.arange(50, dtype=float) * 0.125 - 1e-3
    msg.dof_total[3] = 1.2345e-4  # a rotation, in degrees
    msg.valid = True
    msg.status = "ok: 4/4 corners"
    msg.wavefront_rms_nm = 187.25
    msg.predicted_residual_rms_nm = 31.5
    msg.dry_run = True
    msg.n_modes_used = 37
    return msg


def _sample_corner_wavefront():
    msg = _msg_class("CornerWavefront")()
    msg.header.stamp.sec = 12
    msg.header.frame_id = "focal_plane"
    msg.corner = "R40"
    msg.field_deg = [-1.1902, 1.1902]
    msg.field_intra_deg = [-1.1902, 1.1802]
    msg.field_extra_deg = [-1.1902, 1.2002]
    msg.noll = list(range(4, 23))
    msg.zernikes_nm = [float(j) * 10.0 - 50.0 for j in range(4, 23)]
    msg.uncertainty_nm = [2.5] * 19
    msg.n_pairs = 3
    msg.caustic = False
    msg.valid = False
    msg.status = "too few donuts"
    msg.solver = "exp"
    msg.iterations = 14
    msg.compute_ms = 42.5
    return msg


def test_dof_correction_serialization_round_trip():
    from rclpy.serialization import deserialize_message, serialize_message

    cls = _msg_class("DofCorrection")
    msg = _sample_dof_correction()
    raw = serialize_message(msg)
    assert isinstance(raw, bytes)
    # CDR: 4-byte encapsulation + header + 2 x 50 doubles + scalars.
    assert len(raw) > 2 * 50 * 8
    back = deserialize_message(raw, cls)
    assert back == msg
    np.testing.assert_array_equal(back.dof, msg.dof)
    np.testing.assert_array_equal(back.dof_total, msg.dof_total)
    assert back.dof.shape == (50,)
    assert back.header.stamp.sec == 1_700_000_123
    assert back.header.stamp.nanosec == 456_789
    assert back.header.frame_id == "telescope"
    assert back.valid is True and back.dry_run is True
    assert back.status == "ok: 4/4 corners"
    assert back.wavefront_rms_nm == 187.25
    assert back.predicted_residual_rms_nm == 31.5
    assert back.n_modes_used == 37


def test_corner_wavefront_serialization_round_trip():
    from rclpy.serialization import deserialize_message, serialize_message

    msg = _sample_corner_wavefront()
    back = deserialize_message(serialize_message(msg), _msg_class("CornerWavefront"))
    assert back == msg
    assert list(back.noll) == list(range(4, 23))
    assert math.isclose(back.compute_ms, 42.5)
    assert back.status == "too few donuts"


@pytest.mark.ros
def test_wavefront_vector_pub_sub_over_dds(ros_context):
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    wv_cls = _msg_class("WavefrontVector")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub_node = rclpy.create_node("wv_pub", context=ros_context)
    sub_node = rclpy.create_node("wv_sub", context=ros_context)
    received = []
    sub_node.create_subscription(wv_cls, "wavefront", received.append, qos)
    pub = pub_node.create_publisher(wv_cls, "wavefront", qos)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(pub_node)
    executor.add_node(sub_node)

    msg = wv_cls()
    msg.header.frame_id = "focal_plane"
    msg.zernikes_nm = np.arange(76, dtype=float) * 1.5 - 20.0
    msg.corner_valid = [True, False, True, True]
    msg.corners = ["R00", "R04", "R40", "R44"]
    msg.status = "R04: caustic"
    try:
        deadline = time.monotonic() + 15.0
        while not received and time.monotonic() < deadline:
            if pub.get_subscription_count() > 0:
                msg.header.stamp = pub_node.get_clock().now().to_msg()
                pub.publish(msg)
            executor.spin_once(timeout_sec=0.1)
    finally:
        executor.shutdown()
        pub_node.destroy_node()
        sub_node.destroy_node()

    assert received, "no WavefrontVector received over DDS within 15 s"
    got = received[0]
    np.testing.assert_array_equal(got.zernikes_nm, msg.zernikes_nm)
    assert list(got.corner_valid) == [True, False, True, True]
    assert list(got.corners) == ["R00", "R04", "R40", "R44"]
    assert got.status == "R04: caustic"
    assert got.header.frame_id == "focal_plane"


# --- bag compatibility (rosbags) ------------------------------------------------------------


@pytest.fixture(scope="module")
def typestore(repo_root):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for name in MSG_NAMES:
        text = (repo_root / "msg_defs" / "msg" / f"{name}.msg").read_text()
        store.register(get_types_from_msg(text, f"cwfs_msgs/msg/{name}"))
    return store


def _compiled_type_hash(name: str) -> str:
    """RIHS01 hash compiled into libcwfs_msgs__rosidl_generator_c (what DDS advertises)."""

    class TypeHash(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint8), ("value", ctypes.c_uint8 * 32)]

    lib = ctypes.CDLL(str(_cwfs_msgs_prefix() / "lib" / "libcwfs_msgs__rosidl_generator_c.so"))
    fn = getattr(lib, f"cwfs_msgs__msg__{name}__get_type_hash")
    fn.restype = ctypes.POINTER(TypeHash)
    fn.argtypes = [ctypes.c_void_p]
    h = fn(None).contents
    return f"RIHS{h.version:02d}_" + bytes(h.value).hex()


@pytest.mark.parametrize("name", MSG_NAMES)
def test_rosbags_type_hash_matches_rosidl(typestore, name):
    desc = json.loads(
        (_cwfs_msgs_prefix() / "share" / "cwfs_msgs" / "msg" / f"{name}.json").read_text()
    )
    hashes = {h["type_name"]: h["hash_string"] for h in desc["type_hashes"]}
    rosidl_hash = hashes[f"cwfs_msgs/msg/{name}"]
    assert rosidl_hash.startswith("RIHS01_")
    assert typestore.hash_rihs01(f"cwfs_msgs/msg/{name}") == rosidl_hash
    assert _compiled_type_hash(name) == rosidl_hash


def test_rosbags_reads_rclpy_cdr(typestore):
    """rclpy's CDR decodes in rosbags, and rosbags' CDR decodes in rclpy to the same message.

    Bytes are compared by length only: alignment padding is not zeroed by FastCDR.
    """
    from rclpy.serialization import deserialize_message, serialize_message

    msg = _sample_dof_correction()
    raw = serialize_message(msg)
    decoded = typestore.deserialize_cdr(raw, "cwfs_msgs/msg/DofCorrection")
    np.testing.assert_array_equal(decoded.dof, msg.dof)
    np.testing.assert_array_equal(decoded.dof_total, msg.dof_total)
    assert decoded.header.stamp.sec == msg.header.stamp.sec
    assert decoded.header.frame_id == "telescope"
    assert decoded.status == msg.status
    assert decoded.n_modes_used == 37 and decoded.dry_run is True
    reencoded = typestore.serialize_cdr(decoded, "cwfs_msgs/msg/DofCorrection")
    assert len(reencoded) == len(raw)
    assert deserialize_message(bytes(reencoded), _msg_class("DofCorrection")) == msg

    cw = _sample_corner_wavefront()
    raw_cw = serialize_message(cw)
    decoded_cw = typestore.deserialize_cdr(raw_cw, "cwfs_msgs/msg/CornerWavefront")
    assert list(decoded_cw.noll) == list(range(4, 23))
    reencoded_cw = typestore.serialize_cdr(decoded_cw, "cwfs_msgs/msg/CornerWavefront")
    assert len(reencoded_cw) == len(raw_cw)
    assert deserialize_message(bytes(reencoded_cw), _msg_class("CornerWavefront")) == cw
