"""wavefront_node's input side, from the outside: counts that wrapped inside a converter
narrower than the image type, a clip on a zero background, stamp 0, images too large to pair,
images stamped a few seconds ahead, another corner's or an untrusted publisher's images, and
the drops of several publishers on one topic (docs/reliability.md). Library checks first,
then over real DDS: one corner (R00), one worker."""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import of
from scipy.ndimage import gaussian_filter

from cwfs_ros.runtime.images import ImageDecodeError, decode_checked

T = 1_750_000_000_000_000_000
SEC = 1_000_000_000


def donut_shape(n: int = 160, radius_px: float = 60.0, seeing_px: float = 1.5) -> np.ndarray:
    """An annulus blurred by the seeing (1.5 px sigma: 0.7 arcsec FWHM at 0.2 arcsec/px),
    peak 1."""
    yy, xx = np.mgrid[0:n, 0:n] - (n - 1) / 2.0
    r = np.hypot(xx, yy)
    a = gaussian_filter(((r <= radius_px) & (r >= 0.61 * radius_px)).astype(float), seeing_px)
    return a / a.max()


def counts(bits: int, peak_fraction: float, bias_fraction: float, seed: int,
           wrap: bool = False, seeing_px: float = 1.5) -> np.ndarray:
    """Raw counts of a ``bits``-bit converter (Poisson light, bias, 5 ADU read noise), the
    peak at ``peak_fraction`` of its range; past the range they wrap (``wrap``) or clip."""
    rng = np.random.default_rng(seed)
    top = float(2 ** bits)
    bias = bias_fraction * top
    shape = donut_shape(seeing_px=seeing_px)
    x = np.round(rng.poisson(shape * (peak_fraction * top - bias)) + bias
                 + rng.normal(0.0, 5.0, shape.shape))
    return np.mod(x, top) if wrap else np.clip(x, 0, top - 1)


def reason(a: np.ndarray, encoding: str = "16UC1") -> str:
    dt = {"16UC1": "<u2", "32SC1": "<i4"}[encoding]
    x = np.ascontiguousarray(a, dtype=dt)
    try:
        decode_checked(x.tobytes(), height=x.shape[0], width=x.shape[1], encoding=encoding,
                       step=x.shape[1] * x.itemsize)
    except ImageDecodeError as exc:
        return exc.reason
    return ""


@pytest.mark.parametrize("bits", [10, 12, 14])
def test_counts_that_wrapped_inside_a_narrower_converter_are_refused(bits):
    for k, over in enumerate((1.05, 1.2, 1.5, 2.5)):
        a = counts(bits, over, 0.05, seed=k, wrap=True)
        assert a.max() < 2 ** bits  # in the 16-bit type, far below its range
        assert reason(a) == "wrapped", (bits, over)


def test_an_18_bit_wrap_in_32sc1_is_refused():
    assert reason(counts(18, 1.4, 0.01, seed=3, wrap=True), "32SC1") == "wrapped"


def test_genuine_counts_of_any_converter_depth_are_taken():
    for bits in (10, 12, 14, 16):
        for k, (peak, bias) in enumerate([(0.5, 0.01), (0.75, 0.05), (0.9, 0.1),
                                          (0.98, 0.02)]):
            assert reason(counts(bits, peak, bias, seed=100 + k)) == "", (bits, peak, bias)
    # Sharp edges (no seeing blur): the light steps from the bias to the top quarter of the
    # 12-bit range in one pixel, as a wrap does, but nothing lies below the bias.
    for k, peak in enumerate((0.8, 0.9, 0.98)):
        assert reason(counts(12, peak, 0.05, seed=200 + k, seeing_px=0.3)) == "", peak


def test_adc_depth():
    from cwfs_ros.runtime.images import adc_depth

    u2, i4 = np.dtype("u2"), np.dtype("i4")
    assert adc_depth((0.0, 4095.0), u2) == 12
    assert adc_depth((0.0, 4096.0), u2) == 13
    assert adc_depth((0.0, 40000.0), u2) is None  # the type's own range
    assert adc_depth((0.0, 300.0), u2) is None  # too few levels to judge
    assert adc_depth((-1.0, 4095.0), i4) is None  # negative: not a raw ADC
    assert adc_depth((0.0, 2.0 ** 18 - 1), i4) == 18


def test_a_wrap_at_the_converter_depth_is_told_from_a_sharp_edge():
    from cwfs_ros.runtime.images import background_floor

    # With a bias: wrapped light falls below the background.
    a = counts(12, 1.2, 0.05, seed=11, wrap=True)
    assert 150 < background_floor(a) < 205  # bias 205 ADU, read noise 5 ADU
    assert reason(a) == "wrapped"
    # Without one (a background of 0): wrapped pixels lie buried in the light, with 3 or 4
    # of their neighbours in the top quarter; a sharp edge, from the light at 98 % of the
    # range straight to 0, leaves its background pixels 1 or 2.
    assert background_floor(np.zeros((160, 160))) < 0
    rng = np.random.default_rng(12)
    shape = donut_shape(seeing_px=0.3)
    for bits, over in ((10, 1.03), (12, 1.01)):  # the light's noise straddles the wrap
        top = 2 ** bits
        assert reason(np.mod(rng.poisson(shape * over * top), top)) == "wrapped", bits
        for peak in (0.9, 0.98):
            assert reason(np.minimum(rng.poisson(shape * peak * top), top - 1)) == "", peak


def test_a_clip_below_full_scale_on_a_zero_background_is_saturated_not_wrapped():
    shape = donut_shape(seeing_px=0.3)  # sharp edges: the light drops to 0 in one pixel
    rng = np.random.default_rng(5)
    light = rng.poisson(shape * 2000.0).astype(float)
    for frac in (0.5, 0.8, 0.95):
        level = np.quantile(light[light > 0], frac)
        clipped = np.round(np.minimum(light, level) / level * 0.97 * 65535)
        assert reason(clipped) == "saturated", frac
    # A 12-bit converter clipping at 4095 with a bias is never called wrapped (the decoder
    # takes a smooth clipped donut: the estimator's plateau test refuses it).
    assert reason(counts(12, 1.3, 0.05, seed=8)) in ("", "saturated")


def test_sequence_gaps_with_several_publishers_are_a_lower_bound():
    from cwfs_ros.ros.common import SequenceGaps

    g = SequenceGaps()
    for seq in (1, 2, 5):
        g.note({"publication_sequence_number": seq}, 1)
    assert g.dropped == 2 and g.exact and g.describe() == "2"
    # A second publisher: its numbers (1, 2, ...) interleave with the first's; nothing is
    # compared while both are matched, so nothing is invented.
    for seq in (6, 1, 7, 2, 9, 3):
        assert g.note({"publication_sequence_number": seq}, 2) == 0
    assert g.dropped == 2 and not g.exact and g.describe().startswith("at least 2 (6 ")
    # One publisher left: counted again from its next message on.
    for seq in (20, 21, 24):
        g.note({"publication_sequence_number": seq}, 1)
    assert g.dropped == 4


def test_the_pipeline_refuses_stamp_0_and_oversized_pairs_before_decoding():
    pytest.importorskip("sensor_msgs")
    from sensor_msgs.msg import Image as Msg

    from cwfs_ros.cli.replay import node_parameters
    from cwfs_ros.runtime.pipeline import WavefrontPipeline

    p = node_parameters("wavefront_node")
    pipe = WavefrontPipeline(p.__getitem__, ["R00"])
    clock = T + 10 * SEC

    def msg(stamp_ns: int, side_px: int, data: bytes = b"") -> Msg:
        m = Msg(height=side_px, width=side_px, encoding="16UC1", step=2 * side_px, data=data)
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, SEC)
        return m

    zero = pipe.refusal(msg(0, 160), "R00", "intra", clock)
    assert zero is not None and zero.reason == "no_stamp"
    assert pipe.refused_record(zero, 0.0) is None  # stamp 0 names no visit: not paired
    # 8192 x 8192: 537 MB as float64, a pair 1074 MB > 256 MB. Judged without the data.
    big = pipe.refusal(msg(T, 8192), "R00", "intra", clock)
    assert big is not None and big.reason == "too_large" and "1074 MB" in big.message
    assert pipe.refusal(msg(T, 4000), "R00", "intra", clock) is None  # 2 x 128 MB fit 256
    p["max_pending_mb"] = 200.0
    assert pipe.refusal(msg(T, 4000), "R00", "intra", clock).reason == "too_large"
    # A refused image still pairs: the corner's result names its reason, not "unpaired".
    rec = pipe.refused_record(big, 0.0)
    assert rec is not None and rec.image is None and rec.reason == "too_large"
    pipe.add_record(rec)
    good, _ = pipe.record(msg(T, 160, data=np.full((160, 160), 1000, "<u2").tobytes()),
                          "R00", "extra", 0.1)
    step = pipe.add_record(good)
    assert step.pair is not None and step.pair.reason == "too_large"
    out = pipe.job_for(step.pair)
    assert not out.valid and out.reason == "too_large"


# ---------------------------------------------------------------------------- over DDS
rclpy = pytest.importorskip("rclpy")

from sensor_msgs.msg import Image  # noqa: E402

from cwfs_ros.ros.common import IMAGE_QOS  # noqa: E402
from cwfs_ros.ros.convert import image_msg  # noqa: E402
from cwfs_ros.runtime.corner_pool import synthetic_donut  # noqa: E402

DONUT = synthetic_donut(160, 60.0, 0.61)


@pytest.fixture
def graph(r00_graph):
    """A wavefront node serving R00 (the bundled parameters but the corners, workers and
    timeout) and a camera node with its publishers and recorders (conftest's
    ``r00_graph``)."""
    return lambda **params: r00_graph(tester="camera", diagnostics_period_s=0.2, **params)

def test_images_stamped_zero_are_refused_and_publish_no_valid_wavefront(graph):
    from conftest import wait_for

    wf, _, pub, corner, vector = graph()
    for s in ("intra", "extra"):
        pub[s].publish(image_msg(DONUT, 0))
    wait_for(lambda: wf.rejected.counts["no_stamp"] == 2, 10, "two refusals")
    time.sleep(1.5)  # past the visit timeout: nothing was paired or assembled
    assert not [m for m in corner if m.valid] and not [v for v in vector if v.corner_valid[0]]
    assert wf.stats["pairs"] == 0 and wf.pairing.pending_count() == 0
    good = T + 1 * SEC  # the node still works
    for s in ("intra", "extra"):
        pub[s].publish(image_msg(DONUT, good))
    wait_for(lambda: of(corner, good), 20, "the good corner")
    assert of(corner, good)[0].valid


def test_an_image_of_another_corner_makes_its_corner_say_so_at_once(graph):
    from conftest import wait_for

    wf, _, pub, corner, vector = graph(visit_timeout_s=30.0)
    s = T + 2 * SEC
    pub["intra"].publish(image_msg(DONUT, s, frame_id="R44_SW1"))
    pub["extra"].publish(image_msg(DONUT, s))
    t0 = time.monotonic()
    wait_for(lambda: of(corner, s), 10, "the corner's result")
    assert time.monotonic() - t0 < 5.0  # not after the 30 s pairing timeout
    (c,) = of(corner, s)
    assert not c.valid and "frame_mismatch" in c.status and "unpaired" not in c.status, c.status
    assert wf.rejected.counts["frame_mismatch"] == 1 and wf.rejected.counts["unpaired"] == 0


def test_images_a_few_seconds_ahead_are_refused_with_the_default_tolerance(graph):
    from conftest import wait_for

    wf, _, pub, corner, _ = graph()
    assert wf.get_parameter("max_future_s").value == 1.0
    now = time.time_ns()
    ahead = now + 9 * SEC
    for s in ("intra", "extra"):
        pub[s].publish(image_msg(DONUT, ahead))
    wait_for(lambda: wf.rejected.counts["future_stamp"] == 2, 10, "refusals")
    good = now - 2 * SEC  # a genuine exposure: stamped before it arrives
    for s in ("intra", "extra"):
        pub[s].publish(image_msg(DONUT, good))
    wait_for(lambda: of(corner, good), 20, "the good corner")
    assert of(corner, good)[0].valid and not of(corner, ahead)


def test_an_image_too_large_to_pair_is_refused_before_decoding(graph):
    from conftest import wait_for

    wf, _, pub, corner, _ = graph(max_pending_mb=64.0, visit_timeout_s=30.0)
    s = T + 3 * SEC
    big = np.zeros((2048, 2048), np.uint16)  # 33.6 MB as float64: a pair is 67 MB
    decoded = []
    orig = wf.pipeline.record

    def record(msg, *a, **k):
        decoded.append(msg.height)
        return orig(msg, *a, **k)

    wf.pipeline.record = record
    pub["intra"].publish(image_msg(big, s, encoding="16UC1"))
    pub["extra"].publish(image_msg(DONUT, s))
    wait_for(lambda: of(corner, s), 20, "the corner's result")
    (c,) = of(corner, s)
    assert not c.valid and "too_large" in c.status, c.status
    assert wf.rejected.counts["too_large"] == 1 and 2048 not in decoded
    assert wf.pairing.pending_count() == 0


def test_a_second_publisher_on_an_image_topic_is_named_and_its_images_refused(graph):
    from conftest import wait_for

    wf, cam, pub, corner, vector = graph()
    s = T + 4 * SEC
    for side in ("intra", "extra"):
        pub[side].publish(image_msg(DONUT, s))
    wait_for(lambda: of(corner, s), 20, "the genuine corner")
    assert of(corner, s)[0].valid
    kv = {x.key: x.value for x in wf.diagnostics().values}
    assert not any(k.startswith("publishers.") for k in kv)
    other = rclpy.create_node("camera", context=cam.context)  # an impostor named alike
    try:
        imp = other.create_publisher(Image, "aos/wfs/R00/extra/image", IMAGE_QOS)
        wait_for(lambda: imp.get_subscription_count() > 0, 10, "discovery")
        wait_for(lambda: "publishers.R00.extra" in
                 {x.key for x in wf.diagnostics().values}, 10, "the topic named")
        st = wf.diagnostics()
        kv = {x.key: x.value for x in st.values}
        assert kv["publishers.R00.extra"].startswith("2: /camera (gid "), kv
        assert st.level == b"\x01" and "untrusted_source" in st.message, st.message
        # A chimeric visit: intra of one exposure, extra of another under its stamp.
        c = T + 5 * SEC
        pub["intra"].publish(image_msg(DONUT, c))
        imp.publish(image_msg(synthetic_donut(160, 58.0, 0.61), c))
        wait_for(lambda: of(corner, c), 20, "the corner's result")
        (m,) = of(corner, c)
        assert not m.valid and "untrusted_source" in m.status, m.status
        assert wf.rejected.counts["untrusted_source"] == 1
    finally:
        other.destroy_node()


def test_a_camera_that_sends_one_visit_and_leaves_is_refused(graph):
    """An impostor camera matches, waits past the settle time, publishes both images of its
    own visit and leaves at once: the topic is back to one publisher when the images are
    taken, but the writers ever matched still count it, so the corner is untrusted_source;
    the genuine camera's next visit is taken once the topic has settled."""
    from conftest import wait_for

    wf, cam, pub, corner, vector = graph()
    other = rclpy.create_node("camera", context=cam.context)
    try:
        imps = {side: other.create_publisher(Image, f"aos/wfs/R00/{side}/image", IMAGE_QOS)
                for side in ("intra", "extra")}
        wait_for(lambda: all(p.get_subscription_count() for p in imps.values()), 10,
                 "discovery")
        time.sleep(2.5)
        h = T + 7 * SEC
        for p in imps.values():
            p.publish(image_msg(DONUT, h))
        for p in imps.values():
            other.destroy_publisher(p)
    finally:
        other.destroy_node()
    wait_for(lambda: of(corner, h), 20, "the impostor visit's result")
    (m,) = of(corner, h)
    assert not m.valid and "untrusted_source" in m.status, m.status
    assert not [v for v in of(vector, h) if v.valid]
    g = T + 8 * SEC
    wait_for(lambda: wf._image_trust[("R00", "intra")].problem() is None
             and wf._image_trust[("R00", "extra")].problem() is None, 15, "trust back")
    for side in ("intra", "extra"):
        pub[side].publish(image_msg(DONUT, g))
    wait_for(lambda: of(corner, g), 20, "the genuine corner")
    assert of(corner, g)[0].valid, of(corner, g)[0].status


def test_several_publishers_are_taken_when_allowed_and_their_drops_a_lower_bound(graph):
    from conftest import wait_for

    wf, cam, pub, corner, _ = graph(max_image_publishers=0)
    other = rclpy.create_node("camera2", context=cam.context)
    try:
        imp = other.create_publisher(Image, "aos/wfs/R00/intra/image", IMAGE_QOS)
        wait_for(lambda: imp.get_subscription_count() > 0, 10, "discovery")
        for _ in range(5):  # the second publisher's numbers start again from 1
            imp.publish(image_msg(DONUT, T - 100 * SEC))
        c = T + 6 * SEC
        pub["intra"].publish(image_msg(DONUT, c))
        pub["extra"].publish(image_msg(DONUT, c))
        wait_for(lambda: of(corner, c), 20, "the corner")
        assert of(corner, c)[0].valid
        g = wf.image_gaps[("R00", "intra")]
        assert not g.exact and g.dropped == 0
        kv = {x.key: x.value for x in wf.diagnostics().values}
        assert kv["queue_dropped.R00.intra"].startswith("at least 0 ("), kv
        assert kv["publishers.R00.intra"].startswith("2: "), kv
    finally:
        other.destroy_node()
