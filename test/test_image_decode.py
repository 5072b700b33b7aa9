"""Image decoding from raw sensor_msgs/Image fields, orientation, padding, and msg conversion.

Expected pixel values are built here with numpy from known arrays, independently of the code
under test.
"""

from __future__ import annotations

import array

import numpy as np
import pytest

from cwfs_ros.errors import ImageError
from cwfs_ros.runtime.images import ENCODINGS, ImageDecodeError, decode_image, decoded_dtype
from cwfs_ros.wfs.orientation import Orientation, orient_image, pad_stamp

RNG = np.random.default_rng(3)
# encoding -> numpy type of the pixels
CASES = {
    "32FC1": np.float32, "64FC1": np.float64, "16UC1": np.uint16, "mono16": np.uint16,
    "32SC1": np.int32, "16SC1": np.int16, "8UC1": np.uint8, "mono8": np.uint8,
    "8SC1": np.int8,
}


def sample(dtype, shape=(7, 5)) -> np.ndarray:
    if np.issubdtype(dtype, np.floating):
        return (RNG.normal(size=shape) * 1e3).astype(dtype)
    info = np.iinfo(dtype)
    return RNG.integers(info.min, info.max, size=shape, endpoint=True).astype(dtype)


def raw(a: np.ndarray, big: bool = False, row_pad: int = 0) -> tuple[bytes, int]:
    """Bytes of ``a`` in the given byte order, each row followed by ``row_pad`` junk bytes."""
    b = a.astype(a.dtype.newbyteorder(">" if big else "<"))
    rows = [r.tobytes() + bytes([0xAB]) * row_pad for r in b]
    return b"".join(rows), a.shape[1] * a.dtype.itemsize + row_pad


def test_supported_encodings_cover_the_required_ones():
    assert {"32FC1", "64FC1", "16UC1", "32SC1"} <= set(ENCODINGS)
    assert set(CASES) == set(ENCODINGS)


@pytest.mark.parametrize("encoding", sorted(CASES))
@pytest.mark.parametrize("big", [False, True])
@pytest.mark.parametrize("row_pad", [0, 3])
def test_decode_every_encoding_byte_order_and_row_padding(encoding, big, row_pad):
    a = sample(CASES[encoding])
    data, step = raw(a, big, row_pad)
    out = decode_image(data, height=a.shape[0], width=a.shape[1], encoding=encoding,
                       step=step, is_bigendian=big)
    # The narrowest float type that holds every value of the encoding exactly.
    exact32 = encoding in ("mono8", "8UC1", "8SC1", "mono16", "16UC1", "16SC1", "32FC1")
    assert out.dtype == (np.float32 if exact32 else np.float64) == decoded_dtype(encoding)
    assert out.dtype.isnative and out.shape == a.shape
    np.testing.assert_array_equal(out, a.astype(np.float64))


def test_an_unpadded_native_float_frame_is_decoded_without_a_copy():
    a = sample(np.float32, (40, 30))
    data = bytearray(a.astype("<f4").tobytes())
    out = decode_image(data, height=40, width=30, encoding="32FC1", step=120)
    # A read-only view of the message's buffer: nothing downstream can write into it.
    assert np.shares_memory(out, np.frombuffer(data, np.uint8)) and not out.flags.writeable
    np.testing.assert_array_equal(out, a)
    padded, step = raw(a, row_pad=4)  # padded rows, or the other byte order: a new array
    assert decode_image(padded, height=40, width=30, encoding="32FC1", step=step).flags.writeable
    swapped, step = raw(a, big=True)
    out = decode_image(swapped, height=40, width=30, encoding="32FC1", step=step,
                       is_bigendian=True)
    assert out.flags.writeable and out.dtype.isnative
    np.testing.assert_array_equal(out, a)


@pytest.mark.parametrize("container", [bytes, bytearray, lambda b: array.array("B", b),
                                       lambda b: np.frombuffer(b, np.uint8), list])
def test_decode_accepts_the_containers_rclpy_and_users_pass(container):
    a = sample(np.float32, (3, 4))
    data, step = raw(a)
    out = decode_image(container(data), height=3, width=4, encoding="32FC1", step=step)
    np.testing.assert_array_equal(out, a)


@pytest.mark.parametrize(
    "kw, reason",
    [
        ({"encoding": "rgb8"}, "unsupported_encoding"),
        ({"encoding": "32FC3"}, "unsupported_encoding"),
        ({"encoding": "bayer_rggb8"}, "unsupported_encoding"),
        ({"encoding": ""}, "unsupported_encoding"),
        ({"step": 4 * 4 - 1}, "bad_step"),  # shorter than a row of 4 float32
        ({"step": 0}, "bad_step"),
        ({"height": 0}, "bad_dimensions"),
        ({"width": 0}, "bad_dimensions"),
        ({"height": -3}, "bad_dimensions"),
        ({"width": 100_000}, "bad_dimensions"),
        ({"data_cut": 1}, "truncated_data"),
        ({"data_cut": 16}, "truncated_data"),
        ({"data_cut": -4}, "excess_data"),
        ({"step": 4 * 4 + 8}, "truncated_data"),  # step claims padding the data lacks
    ],
)
def test_decode_rejects_malformed_fields_with_a_named_reason(kw, reason):
    a = sample(np.float32, (3, 4))
    data, step = raw(a)
    cut = kw.pop("data_cut", 0)
    if cut > 0:
        data = data[:-cut]
    elif cut < 0:
        data = data + b"\0" * -cut
    fields = {"height": 3, "width": 4, "encoding": "32FC1", "step": step, **kw}
    with pytest.raises(ImageDecodeError) as ei:
        decode_image(data, **fields)
    assert ei.value.reason == reason
    assert str(ei.value).startswith(reason + ":")
    assert isinstance(ei.value, ImageError)  # the node's generic image-error path catches it


def test_decode_error_messages_are_specific():
    with pytest.raises(ImageDecodeError, match="'rgb8' is not supported.*32FC1"):
        decode_image(b"\0" * 12, height=2, width=2, encoding="rgb8", step=6)
    with pytest.raises(ImageDecodeError, match="47 B of data for step 16 x height 3 = 48 B"):
        decode_image(b"\0" * 47, height=3, width=4, encoding="32FC1", step=16)


def test_decode_keeps_nan_and_tiny_images_for_the_estimator_to_judge():
    a = np.array([[np.nan]], dtype=np.float32)
    out = decode_image(a.tobytes(), height=1, width=1, encoding="32FC1", step=4)
    assert out.shape == (1, 1) and np.isnan(out[0, 0])


def test_orientation_rotates_then_flips():
    a = np.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(orient_image(a, Orientation()), a)
    np.testing.assert_array_equal(orient_image(a, Orientation(1)), np.rot90(a))
    np.testing.assert_array_equal(orient_image(a, Orientation(2, "lr")), np.rot90(a, 2)[:, ::-1])
    np.testing.assert_array_equal(orient_image(a, Orientation(3, "ud")), np.rot90(a, 3)[::-1])
    np.testing.assert_array_equal(orient_image(a, Orientation(5)), np.rot90(a))  # modulo 4
    # rot90 by 2 == flipping both axes
    np.testing.assert_array_equal(orient_image(a, Orientation(2)), a[::-1, ::-1])
    with pytest.raises(ValueError):
        Orientation(0, "diagonal")


def test_pad_stamp_uses_the_border_median():
    a = np.full((6, 6), 7.0)
    a[2:4, 2:4] = 100.0
    a[0, 0] = np.nan  # ignored for the fill
    p = pad_stamp(a, 3)
    assert p.shape == (12, 12)
    np.testing.assert_array_equal(p[3:9, 3:9], a)
    assert np.all(p[:3] == 7.0) and np.all(p[:, -3:] == 7.0)
    assert pad_stamp(a, 0) is a


# ------------------------------------------------------------------ message conversion
def test_image_msg_round_trip_through_the_node_converter():
    pytest.importorskip("sensor_msgs")
    from cwfs_ros.ros.convert import image_msg, image_record_from_msg

    # Counts of a detector (the node's decoder refuses full-scale and wrapped ones).
    a = RNG.integers(-100_000, 1_000_000, size=(5, 9)).astype(np.float64)
    for enc in ("32SC1", "64FC1"):
        for big in (False, True):
            m = image_msg(a, 1_700_000_000_123_456_789, encoding=enc, big_endian=big,
                          frame_id="fp")
            rec = image_record_from_msg(m, "R04", "extra", 5.0)
            assert rec.error is None and rec.stamp_ns == 1_700_000_000_123_456_789
            assert (rec.corner, rec.side, rec.frame_id, rec.received) == ("R04", "extra", "fp",
                                                                         5.0)
            np.testing.assert_array_equal(rec.image, a)


def test_bad_image_msg_gives_a_record_with_the_reason():
    pytest.importorskip("sensor_msgs")
    from sensor_msgs.msg import Image

    from cwfs_ros.ros.convert import image_record_from_msg

    m = Image(height=160, width=160, encoding="32FC1", step=640)
    m.data = b"\0" * 1000  # truncated
    rec = image_record_from_msg(m, "R00", "intra", 0.0)
    assert rec.image is None and rec.error.startswith("truncated_data:")
    assert rec.reason == "truncated_data"
    m = Image(height=2, width=2, encoding="bgr8", step=6, data=b"\0" * 12)
    rec = image_record_from_msg(m, "R00", "intra", 0.0)
    assert rec.error.startswith("unsupported_encoding:") and rec.reason == "unsupported_encoding"
