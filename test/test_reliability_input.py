"""Bad pixels that still look like a donut: byte order, wrapped counts, saturation, scale.

Each case is built here from ray-traced donuts (batoid, via ``test_input_checks._expected``)
with numpy: what it holds (bytes swapped, counts wrapped, clipped, scaled) is known by
construction. The message path is the node's: an ``Image`` message decoded by
``image_record_from_msg``; the estimator is run where the check lives there. Rates over many
genuine donuts: ``bench/bench_reliability_checks.py`` (docs/reliability.md).
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("sensor_msgs")

from test_input_checks import _estimate, _expected  # noqa: E402

from cwfs_ros.errors import SaturatedImageError  # noqa: E402
from cwfs_ros.ros.convert import image_msg, image_record_from_msg  # noqa: E402
from cwfs_ros.runtime.images import ImageDecodeError, decode_checked  # noqa: E402
from cwfs_ros.wfs.instrument import load_instrument  # noqa: E402


def _reason(a: np.ndarray, encoding: str, big: bool = False,
            declared_big: bool | None = None) -> str:
    """'' when the node's decoder takes the image, else the reason it gives."""
    m = image_msg(a, 1_700_000_000_000_000_000, encoding=encoding, big_endian=big)
    if declared_big is not None:
        m.is_bigendian = int(declared_big)
    rec = image_record_from_msg(m, "R00", "intra", 0.0)
    return rec.reason


def _counts(scale: float, bias: float, seed: int = 0) -> np.ndarray:
    """Raw counts: the R00 intra donut at ``scale`` counts per unit flux plus a bias."""
    e_in, _ = _expected("R00", True)
    rng = np.random.default_rng(seed)
    return rng.poisson(e_in / e_in.max() * scale + bias).astype(np.int64)


# ------------------------------------------------------------------ byte order
@pytest.mark.parametrize("scale,bias", [(40, 0), (300, 100), (3000, 1000), (20000, 10000)])
def test_swapped_16bit_counts_are_refused_in_either_direction(scale, bias):
    x = _counts(scale, bias)
    assert x.max() < 65535
    assert _reason(x, "16UC1") == "" and _reason(x, "16UC1", big=True) == ""
    # The bytes in one order, the flag saying the other.
    assert _reason(x, "16UC1", big=True, declared_big=False) == "byte_order"
    assert _reason(x, "16UC1", big=False, declared_big=True) == "byte_order"


@pytest.mark.parametrize("encoding,scale", [("32FC1", 1e3), ("64FC1", 1e3), ("32SC1", 5e4)])
def test_swapped_wide_pixels_are_refused(encoding, scale):
    x = _counts(scale, 50.0, seed=1).astype(np.float64)
    assert _reason(x, encoding) == ""
    assert _reason(x, encoding, big=True, declared_big=False) == "byte_order"
    assert _reason(x, encoding, big=False, declared_big=True) == "byte_order"


# ------------------------------------------------------------------ wrapped counts
def test_16bit_unsigned_counts_past_full_scale_that_wrapped_are_refused():
    x = _counts(90_000, 1000)
    assert x.max() > 65535  # the construction passes the full scale
    assert _reason(x % 65536, "16UC1") == "wrapped"
    # Clipped instead (what a converter does): saturated, not wrapped.
    assert _reason(np.minimum(x, 65535), "16UC1") == "saturated"


def test_a_pixel_or_two_wrapped_inside_the_light_are_refused():
    e_in, _ = _expected("R00", True)
    rng = np.random.default_rng(8)
    x = rng.poisson(e_in / e_in.max() * 65535 * 1.01 + 1000.0).astype(np.int64)
    over = int(np.count_nonzero(x > 65535))
    assert 1 <= over <= 3, over  # barely past the full scale
    assert _reason(x % 65536, "16UC1") == "wrapped"


@pytest.mark.parametrize("encoding,bits,scale", [("16SC1", 16, 45_000),
                                                 ("32SC1", 32, 3.0e9)])
def test_signed_counts_wrapping_negative_inside_the_donut_are_refused(encoding, bits, scale):
    x = _counts(scale, 100)
    half = 2 ** (bits - 1)
    assert x.max() >= half
    wrapped = ((x + half) % (2 * half)) - half
    assert wrapped.min() < -half // 2  # negative inside the donut
    assert _reason(wrapped, encoding) == "wrapped"


def test_genuine_bright_counts_are_not_wrapped():
    # Just below the full scale, no wrap: taken.
    x = _counts(60_000, 1000)
    assert x.max() < 65535
    assert _reason(x, "16UC1") == ""


# ------------------------------------------------------------------ saturation and scale
def test_mono8_and_16bit_at_full_scale_are_saturated():
    x = _counts(400, 0)
    assert _reason(np.minimum(x, 255), "mono8") == "saturated"
    assert _reason(np.minimum(_counts(90_000, 0), 65535), "16UC1") == "saturated"


def test_clipped_donut_on_a_zero_background_is_saturated():
    """No noise in the background (exactly 0), photon noise in the donut: the plateau test
    applies (before, it was skipped as a noise-free model image)."""
    e_in, e_ex = _expected("R00", True)
    rng = np.random.default_rng(5)
    a = rng.poisson(e_in * 1e6).astype(np.float64)
    b = rng.poisson(e_ex * 1e6).astype(np.float64)
    edge = np.concatenate([a[:3].ravel(), a[-3:].ravel(), a[:, :3].ravel(), a[:, -3:].ravel()])
    assert np.ptp(edge) == 0.0  # the background is exactly zero
    _estimate(a, b)  # genuine: taken
    clipped = np.minimum(a, np.percentile(a[a > 0], 80))
    with pytest.raises(SaturatedImageError):
        _estimate(clipped, b)


def test_tiny_scaled_float_image_is_bad_scale_not_saturated():
    e_in, _ = _expected("R00", True)
    rng = np.random.default_rng(6)
    a = rng.poisson(e_in * 1e6 + 10.0).astype(np.float64) - 10.0
    assert _reason(a * 1e-300, "64FC1") == "bad_scale"
    clipped = np.minimum(a, np.percentile(a, 95))
    assert _reason(clipped * 1e-300, "64FC1") == "bad_scale"
    assert _reason(a * 1e200, "64FC1") == "bad_scale"
    assert _reason(a * 1e-20, "64FC1") == ""  # small units are fine


def test_decode_checked_raises_with_the_reason():
    x = (_counts(90_000, 1000) % 65536).astype(np.uint16)
    with pytest.raises(ImageDecodeError) as err:
        decode_checked(x.tobytes(), height=x.shape[0], width=x.shape[1], encoding="16UC1",
                       step=2 * x.shape[1])
    assert err.value.reason == "wrapped"


@pytest.mark.parametrize("name", ["lsst", "lsst_poly10", "lsstfam_poly10", "lsst_analytic"])
def test_rubin_instruments_have_a_saturation_level(name):
    level = load_instrument(name).saturation_level
    assert level is not None and 9.0e4 <= level <= 2.0e5
