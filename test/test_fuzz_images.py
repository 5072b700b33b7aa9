"""Property-based tests (hypothesis) of the image-message path: message -> decode -> pair ->
corner estimate, in the library and through a live wavefront_node over DDS.

Properties: nothing raises; every bad message gives an invalid result whose status starts with
a named reason; a result is valid only with 19 finite, physically bounded Zernikes; random
bytes are never a valid wavefront; the node stays alive and answers every visit.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pytest
from conftest import spin_thread, wait_for
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

rclpy = pytest.importorskip("rclpy")

from cwfs_msgs.msg import CornerWavefront  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from cwfs_ros.ros.common import IMAGE_QOS, OUTPUT_QOS, stamp_to_ns  # noqa: E402
from cwfs_ros.ros.convert import image_msg, image_record_from_msg  # noqa: E402
from cwfs_ros.ros.executor import MultiThreadedExecutor  # noqa: E402
from cwfs_ros.ros.wavefront_node import WavefrontNode  # noqa: E402
from cwfs_ros.runtime.corner_pool import CornerJob, run_corner_job  # noqa: E402
from cwfs_ros.runtime.images import ENCODINGS  # noqa: E402
from cwfs_ros.wfs.settings import EstimatorSettings  # noqa: E402

SEC = 1_000_000_000
BPP = {"u1": 1, "i1": 1, "u2": 2, "i2": 2, "i4": 4, "f4": 4, "f8": 8}
# A wavefront estimate beyond this is not physical for the corner sensors at 1.5 mm (their
# donuts fold into caustic long before): a "valid" estimate this large would be a bug.
MAX_PLAUSIBLE_NM = 20_000.0


@lru_cache(maxsize=1)
def donuts() -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    """A ray-traced R00 intra/extra pair (nominal telescope) and its field points."""
    from cwfs_ros.sim import load_corner_geometry, perturbed_telescope
    from cwfs_ros.sim.visit import DonutSpec, render_visit

    g = load_corner_geometry()["R00"]
    specs = [DonutSpec("intra", g.intra_field_deg, g.intra_offset_mm, (0.0, 0.0), 1),
             DonutSpec("extra", g.extra_field_deg, g.extra_offset_mm, (0.0, 0.0), 2)]
    im = render_visit(perturbed_telescope(np.zeros(50), "r"), specs, wavelength_nm=622.0,
                      n_photons=1e5, sky_per_pixel=10.0)
    return im["intra"], im["extra"], tuple(g.intra_field_deg), tuple(g.extra_field_deg)


@dataclass
class Sample:
    """A fuzzed message and what it holds (short repr: hypothesis prints failing cases).

    ``partner`` is the image to pair it with in the other slot when the damage needs one
    (``swapped``: the message holds the extra-focal donut, the partner the intra-focal one);
    None means the genuine donut of the other side.
    """

    msg: Image
    damage: str
    partner: np.ndarray | None = None

    def __repr__(self) -> str:
        m = self.msg
        return (f"Sample({self.damage!r}, {m.height}x{m.width} {m.encoding!r}, step "
                f"{m.step}, bigendian {m.is_bigendian}, {len(m.data)} B)")


@st.composite
def image_messages(draw) -> Sample:
    """An Image message, and what it holds: ``random`` bytes, or a real donut with a named
    ``damage`` (``none``, ``scale``, ``nan``, ``clip`` (saturated), ``swapped`` (intra and
    extra exchanged) ...; ``framing`` when its fields are broken)."""
    structured = draw(st.integers(0, 3)) > 0  # most examples reach the estimator
    bad_encodings = ["rgb8", "bgr8", "yuv422", "", "32FC3"]
    encoding = draw(st.sampled_from(["32FC1", "64FC1", "16UC1", "32SC1"] if structured
                                    else [*ENCODINGS, *bad_encodings]))
    if structured and draw(st.integers(0, 9)) == 0:
        encoding = draw(st.sampled_from([*ENCODINGS, *bad_encodings]))
    big = draw(st.booleans())
    bpp = BPP.get(ENCODINGS.get(encoding, "u1"), 1)
    if structured and encoding in ENCODINGS:
        intra = donuts()[0].astype(np.float64)
        partner = None
        damage = draw(st.sampled_from(["none", "scale", "nan", "inf", "clip", "negate",
                                       "crop", "shift", "constant", "swapped"]))
        if damage == "swapped":
            # The extra-focal donut sent as the intra image, the intra one as its partner.
            intra, partner = donuts()[1].astype(np.float64), donuts()[0]
        elif damage == "scale":
            intra = intra * draw(st.floats(1e-3, 1e3))
        elif damage in ("nan", "inf"):
            r, c = draw(st.integers(0, 159)), draw(st.integers(0, 159))
            intra[r, c] = np.nan if damage == "nan" else np.inf
        elif damage == "clip":
            intra = np.minimum(intra, np.percentile(intra, draw(st.floats(50, 99))))
        elif damage == "negate":
            intra = -intra
        elif damage == "crop":
            k = draw(st.integers(1, 120))
            intra = intra[k // 2: 160 - (k - k // 2), :]
        elif damage == "shift":
            intra = np.roll(intra, draw(st.integers(-60, 60)), axis=draw(st.integers(0, 1)))
        elif damage == "constant":
            intra = np.full_like(intra, draw(st.floats(-10, 10)))
        kind = ENCODINGS[encoding]
        if kind[0] in "ui":
            info = np.iinfo(np.dtype(kind))
            if damage in ("nan", "inf"):
                damage = "none"  # an integer image cannot hold NaN/Inf
            rounded = np.round(np.nan_to_num(intra))
            clipped = np.clip(rounded, info.min, info.max)
            if damage in ("none", "scale") and np.count_nonzero(rounded > info.max) >= \
                    0.01 * rounded.size:
                damage = "clip"  # the integer range saturated the donut (1% of the stamp)
            elif damage == "none" and np.any(rounded < info.min):
                damage = "floor"  # negative background pixels cut at 0: not saturation
            intra = clipped
        msg = image_msg(intra.astype(np.dtype(kind)), 0, encoding=encoding)
        if draw(st.booleans()):  # also damage the framing now and then
            delta = draw(st.integers(-5, 5))
            if delta:
                msg.data = bytes(msg.data)[: len(msg.data) + min(delta, 0)] + \
                    b"\0" * max(delta, 0)
                damage = "framing"
        return Sample(msg, damage, partner)
    h = draw(st.integers(0, 9000 if big else 200))
    w = draw(st.integers(0, 9000 if big else 200))
    step = max(0, w * bpp + draw(st.integers(-3, 8)))
    n = step * h if h * step <= 4_000_000 else 64
    n = max(0, n + draw(st.integers(-4, 4)))
    m = Image(height=h, width=w, encoding=encoding, step=step,
              is_bigendian=int(draw(st.booleans())))
    m.data = draw(st.binary(min_size=min(n, 64), max_size=min(n, 64))) * (n // 64 or 1) \
        if n > 64 else draw(st.binary(min_size=n, max_size=n))
    return Sample(m, "random")


# Damage after which no valid estimate may come out.
MUST_REJECT = {"random", "framing", "nan", "inf", "negate", "constant", "clip", "swapped"}


def _check(out, damage: str) -> None:
    event(f"{damage}: {'valid' if out.valid else out.reason}")
    if out.valid:
        assert damage not in MUST_REJECT, f"{damage} input gave a valid wavefront"
        z = np.asarray(out.zernikes_nm)
        assert z.shape == (19,) and np.all(np.isfinite(z))
        assert np.max(np.abs(z)) < MAX_PLAUSIBLE_NM, z
        assert out.status == "ok"
    else:
        assert out.reason and out.status.startswith(out.reason + ":"), out.status
        assert np.all(np.isnan(out.zernikes_nm))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(sample=image_messages(), side=st.sampled_from(["intra", "extra"]))
def test_message_to_corner_estimate_never_raises_and_flags_bad_input(sample, side):
    msg, damage = sample.msg, sample.damage
    intra, extra, fi, fe = donuts()
    rec = image_record_from_msg(msg, "R00", side, 0.0)
    if rec.error is not None:
        event(f"{damage}: decode {rec.reason}")
        assert rec.image is None and rec.error.startswith(f"{rec.reason}: ")
        return
    if sample.partner is not None:  # the message's image in the intra slot, its partner extra
        a, b = rec.image, sample.partner
    else:
        a, b = (rec.image, extra) if side == "intra" else (intra, rec.image)
    out = run_corner_job(CornerJob("R00", 1, a, b, fi, fe, EstimatorSettings(solver="lsq")))
    _check(out, damage)


@pytest.mark.ros
def test_live_wavefront_node_answers_every_fuzzed_visit(ros_context):
    """Through DDS: each fuzzed intra image with a good extra partner gets one result."""
    ex = MultiThreadedExecutor(num_threads=3, context=ros_context)
    wf = WavefrontNode(context=ros_context, parameter_overrides=[
        Parameter("corners", value=["R00"]), Parameter("workers", value=1),
        Parameter("assemble", value=False), Parameter("solver", value="lsq"),
        Parameter("visit_timeout_s", value=0.5)])
    tester = rclpy.create_node("fuzzer", context=ros_context)
    pubs = {s: tester.create_publisher(Image, f"aos/wfs/R00/{s}/image", IMAGE_QOS)
            for s in ("intra", "extra")}
    got: dict[int, CornerWavefront] = {}
    tester.create_subscription(CornerWavefront, "aos/wfs/R00/wavefront",
                               lambda m: got.__setitem__(stamp_to_ns(m.header.stamp), m),
                               OUTPUT_QOS)
    ex.add_node(wf)
    ex.add_node(tester)
    th = spin_thread(ex)
    th.start()
    extra = donuts()[1]
    counter = iter(range(1, 10_000))
    try:
        wait_for(lambda: wf.ready, 60, "warm-up")
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 10,
                 "discovery")

        @settings(max_examples=25, deadline=None,
                  suppress_health_check=[HealthCheck.too_slow,
                                         HealthCheck.function_scoped_fixture])
        @given(sample=image_messages())
        def one_visit(sample):
            msg, damage = sample.msg, sample.damage
            stamp = (1000 + next(counter)) * SEC
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, SEC)
            pubs["intra"].publish(msg)
            partner = extra if sample.partner is None else sample.partner
            pubs["extra"].publish(image_msg(partner, stamp))
            wait_for(lambda: stamp in got, 20, f"the result of visit {stamp}")
            m = got[stamp]
            if m.valid:
                assert damage not in MUST_REJECT and m.status == "ok"
                assert np.max(np.abs(m.zernikes_nm)) < MAX_PLAUSIBLE_NM
            else:
                assert m.status and ":" in m.status and np.all(np.isnan(m.zernikes_nm))

        one_visit()
        assert wf.ready  # still alive and serving
    finally:
        ex.shutdown(timeout_sec=2.0)
        th.join(5)
        wf.destroy_node()
        tester.destroy_node()
