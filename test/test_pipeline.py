"""WavefrontPipeline: the decisions wavefront_node and the replay share, without a middleware.

The pipeline is driven as the replay drives it, with wavefront_node's parameters from
config/params.yaml (``cwfs_ros.cli.replay.node_parameters``) and real ``sensor_msgs/Image``
messages; jobs that run are run by the workers' own functions.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("sensor_msgs")

from sensor_msgs.msg import Image  # noqa: E402

from cwfs_ros.cli.replay import node_parameters  # noqa: E402
from cwfs_ros.frames.selection import CornerFrameJob  # noqa: E402
from cwfs_ros.layout import CORNERS  # noqa: E402
from cwfs_ros.runtime.corner_pool import CornerJob, CornerOutcome  # noqa: E402
from cwfs_ros.runtime.pipeline import WavefrontPipeline, run_job  # noqa: E402

T0 = 1_700_000_000_000_000_000


def params(**over) -> dict:
    p = node_parameters("wavefront_node")
    p.update(over)
    return p


def image(side_px: int, stamp_ns: int = T0, frame_id: str = "", value: float = 1.0,
          encoding: str = "32FC1") -> Image:
    a = np.full((side_px, side_px), value, dtype="<f4")
    m = Image(height=side_px, width=side_px, encoding=encoding, is_bigendian=0,
              step=side_px * 4, data=a.tobytes())
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    m.header.frame_id = frame_id
    return m


def pair_of(pipe: WavefrontPipeline, corner: str, side_px: int, stamp_ns: int = T0,
            now_s: float = 0.0, value: float = 1.0):
    """Feed both images of a corner; the pair the pipeline formed."""
    for s in ("intra", "extra"):
        rec, bad = pipe.record(image(side_px, stamp_ns, value=value), corner, s, now_s)
        assert bad is None
        step = pipe.add_record(rec)
    assert step.pair is not None and step.rejection is None
    return step.pair


def outcome(corner: str, stamp_ns: int = T0, valid: bool = True) -> CornerOutcome:
    z = np.arange(19, dtype=float) + (0.0 if valid else np.nan)
    return CornerOutcome(corner, stamp_ns, valid, "ok" if valid else "bad: x",
                         "" if valid else "bad", z, (0.0, 0.0), n_pairs=1)


def test_a_pair_becomes_a_stamp_or_a_frame_job_by_size_and_input_mode():
    p = params(**{"sensors.R04.extra.rot90": 2})
    pipe = WavefrontPipeline(p.__getitem__, CORNERS)
    job = pipe.job_for(pair_of(pipe, "R04", 160))
    assert isinstance(job, CornerJob)
    assert job.orient_extra.rot90 == 2 and job.orient_intra.rot90 == 0
    assert job.field_intra_deg == pipe.fields["R04"]["intra"]
    frame = pipe.job_for(pair_of(pipe, "R00", p["frame_min_side_px"]))
    assert isinstance(frame, CornerFrameJob) and frame.corner == "R00"
    assert frame.intra.shape == (p["frame_min_side_px"],) * 2
    # input_mode overrides the size, read per pair (a parameter change takes at once)
    p["input_mode"] = "stamps"
    assert isinstance(pipe.job_for(pair_of(pipe, "R40", 600)), CornerJob)
    p["input_mode"] = "frames"
    assert isinstance(pipe.job_for(pair_of(pipe, "R44", 160)), CornerFrameJob)


def test_an_undecodable_image_gives_the_invalid_outcome_at_once():
    pipe = WavefrontPipeline(params().__getitem__, CORNERS)
    rec, bad = pipe.record(image(160, encoding="bgr8"), "R00", "intra", 0.0)
    assert bad is not None and rec.error
    pipe.add_record(rec)
    rec2, _ = pipe.record(image(160), "R00", "extra", 0.0)
    pair = pipe.add_record(rec2).pair
    out = pipe.job_for(pair)
    assert isinstance(out, CornerOutcome) and not out.valid
    assert out.reason == bad.reason and "intra image" in out.status
    assert run_job(out) is out


def test_frame_jobs_run_as_the_workers_run_them():
    """A flat frame pair through the frame job: an invalid outcome naming the problem (the
    job never raises), not a stamp estimate."""
    pipe = WavefrontPipeline(params().__getitem__, CORNERS)
    out = run_job(pipe.job_for(pair_of(pipe, "R00", 600, value=50.0)))
    assert not out.valid and out.n_pairs == 0 and out.corner == "R00"
    assert out.reason == "flat_or_empty" and "frame is constant (50)" in out.status, out.status


def test_refusals_before_decoding():
    p = params(max_future_s=10.0)
    pipe = WavefrontPipeline(p.__getitem__, CORNERS)
    assert pipe.refusal(image(160), "R00", "intra", T0) is None
    late = pipe.refusal(image(160, T0 + 11 * 10**9), "R00", "intra", T0)
    assert late is not None and late.reason == "future_stamp"
    assert pipe.refusal(image(160, T0 + 11 * 10**9), "R00", "intra", 0) is None  # no clock
    wrong = pipe.refusal(image(160, frame_id="R04_SW1"), "R00", "intra", T0)
    assert wrong is not None and wrong.reason == "frame_mismatch"
    msg = image(160)
    msg.header.stamp.nanosec = 1_000_000_000
    bad = pipe.refusal(msg, "R00", "intra", T0)
    assert bad is not None and bad.reason == "bad_stamp"
    msg = image(160)
    msg.header.stamp.sec = -5
    bad = pipe.refusal(msg, "R00", "intra", T0)
    assert bad is not None and bad.reason == "bad_stamp" and "sec -5 is before 1970" in bad.message
    p["max_future_s"] = 0.0
    assert pipe.refusal(image(160, T0 + 10**12), "R00", "intra", T0) is None


def test_a_conflict_after_pairing_makes_the_corner_invalid():
    pipe = WavefrontPipeline(params().__getitem__, CORNERS)
    pair_of(pipe, "R00", 160)
    rec, _ = pipe.record(image(160, value=2.0), "R00", "intra", 0.1)
    rej = pipe.add_record(rec).rejection
    assert rej is not None and rej.reason == "conflicting_images"
    unpaired, vec = pipe.conflict(rej)
    assert unpaired is None and vec is None
    out, replaced = pipe.settle(outcome("R00"))
    assert replaced and not out.valid and out.reason == "conflicting_images"
    other, replaced = pipe.settle(outcome("R04"))
    assert not replaced and other.valid


def test_a_conflict_while_waiting_closes_the_corner():
    pipe = WavefrontPipeline(params().__getitem__, CORNERS)
    for v in (1.0, 2.0):
        rec, _ = pipe.record(image(160, value=v), "R40", "intra", 0.0)
        step = pipe.add_record(rec)
    unpaired, vec = pipe.conflict(step.rejection)
    assert unpaired is not None and unpaired.corner == "R40" and vec is None
    out = pipe.unpaired_outcome(unpaired)
    assert not out.valid and out.reason == "conflicting_images"


def test_an_unpaired_corner_names_its_partners_refused_stamp():
    """The extra image's stamp is refused (it names no time): its intra partner times out
    ``unpaired``, and the corner's status says what became of the extra image; once an
    extra image of that corner pairs again, or for a refusal before the exposure, it is
    not named."""
    pipe = WavefrontPipeline(params(visit_timeout_s=2.0).__getitem__, CORNERS)
    bad = image(160)
    bad.header.stamp.nanosec = 1_500_000_000
    rej = pipe.refusal(bad, "R04", "extra", T0)
    assert rej is not None and rej.reason == "bad_stamp"
    assert pipe.refused_record(rej, 0.0) is None  # its stamp names no visit: not paired
    rec, _ = pipe.record(image(160), "R04", "intra", 0.0)
    pipe.add_record(rec)
    (unpaired,) = pipe.expire_pairs(10.0)
    out = pipe.unpaired_outcome(unpaired)
    assert not out.valid and out.reason == "unpaired"
    assert "the latest extra image of R04 was refused: bad_stamp" in out.status, out.status
    assert "nanosec 1500000000" in out.status, out.status
    pair_of(pipe, "R04", 160, T0 + 30 * 10**9, now_s=20.0)
    # A refusal before the next visit's exposure belongs to an earlier visit: not named.
    assert pipe.refusal(bad, "R04", "extra", T0 + 45 * 10**9).reason == "bad_stamp"
    rec, _ = pipe.record(image(160, T0 + 60 * 10**9), "R04", "intra", 40.0)
    pipe.add_record(rec)
    (unpaired,) = pipe.expire_pairs(50.0)
    assert "refused" not in pipe.unpaired_outcome(unpaired).status


def test_assembly_expiry_and_closing_the_missing_corners():
    p = params(visit_timeout_s=2.0)
    pipe = WavefrontPipeline(p.__getitem__, CORNERS)
    for c in ("R00", "R04", "R40"):
        vec, rej = pipe.assemble(outcome(c), 0.0)
        assert vec is None and rej is None
    # R44's intra waits; its extra never comes
    rec, _ = pipe.record(image(160), "R44", "intra", 0.0)
    pipe.add_record(rec)
    assert pipe.expire_pairs(1.0) == [] and pipe.expire_visits(1.0) == []
    (vec,) = pipe.expire_visits(2.5)
    assert not vec.complete and list(vec.corner_valid) == [True, True, True, False]
    (closed,) = pipe.close_missing(vec)
    assert closed.corner == "R44" and pipe.pairing.pending_count() == 0
    vec, _ = pipe.assemble(outcome("R00", T0 + 10**9), 3.0)
    assert vec is None
    (vec,) = [v for v in [pipe.assemble(outcome(c, T0 + 10**9), 3.0)[0]
                          for c in ("R04", "R40", "R44")] if v is not None]
    assert vec.complete and vec.stamp_ns == T0 + 10**9


def test_waiting_images_are_bounded_in_memory():
    p = params(max_pending_mb=1.0)
    pipe = WavefrontPipeline(p.__getitem__, CORNERS)
    dropped = []
    for k, c in enumerate(CORNERS):  # 600x600 float32: 1.44 MB each, over the bound alone
        rec, _ = pipe.record(image(600, T0 + k), c, "intra", 0.0)
        dropped += pipe.add_record(rec).dropped
    assert [r.corner for r in dropped] == list(CORNERS)
    assert all(r.reason == "memory_limit" for r in dropped)
    assert pipe.pairing.pending_bytes() <= 1e6


def test_parameter_changes():
    p = params()
    pipe = WavefrontPipeline(p.__getitem__, ["R00"], assemble=False)
    assert pipe.assemble(outcome("R00"), 0.0) == (None, None)
    p["seeing_fwhm_arcsec"] = 0.8
    assert pipe.apply({"seeing_fwhm_arcsec"}) == "seeing"
    assert pipe.settings.seeing_fwhm_arcsec == 0.8
    p["band"] = "g"
    assert pipe.apply({"band"}) == "rewarm" and pipe.settings.band == "g"
    p["pairing_tolerance_s"], p["sensors.R00.intra.flip"] = 0.5, "lr"
    assert pipe.apply({"pairing_tolerance_s", "sensors.R00.intra.flip"}) == ""
    assert pipe.pairing.tolerance_ns == 500_000_000
    assert pipe.orientations[("R00", "intra")].flip == "lr"


def _uint16(side_px: int, top_pixels: int) -> Image:
    rng = np.random.default_rng(side_px)
    a = rng.normal(1000.0, 30.0, (side_px, side_px)).astype("<u2")  # a read-noise background
    a[np.arange(top_pixels) % side_px, np.arange(top_pixels) // side_px + 5] = 65535
    m = Image(height=side_px, width=side_px, encoding="16UC1", is_bigendian=0,
              step=side_px * 2, data=a.tobytes())
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(T0, 1_000_000_000)
    return m


def test_full_scale_pixels_refuse_a_stamp_but_pass_a_frame_to_its_detection():
    """16-bit pixels at 65535: a stamp (one donut) is refused ``saturated`` when it arrives;
    a frame is not, and its job carries the full scale, at which detection calls a star
    saturated whatever the configured level (test_selection)."""
    p = params()
    pipe = WavefrontPipeline(p.__getitem__, CORNERS)
    rec, bad = pipe.record(_uint16(160, 3), "R00", "intra", 0.0)
    assert bad is not None and bad.reason == "saturated" and rec.image is None
    assert "3 pixel(s) at 65535, the full scale of 16UC1" in bad.message, bad.message
    side = p["frame_min_side_px"]
    for s in ("intra", "extra"):
        rec, bad = pipe.record(_uint16(side, 40), "R04", s, 0.0)
        assert bad is None and rec.full_scale_px == 40
        step = pipe.add_record(rec)
    job = pipe.job_for(step.pair)
    assert isinstance(job, CornerFrameJob) and job.full_scale == 65535.0
    floats = pipe.job_for(pair_of(pipe, "R40", side))
    assert isinstance(floats, CornerFrameJob) and floats.full_scale is None


def test_frames_taken_as_stamps_say_which_parameter_to_change():
    """A camera that sends frames to a node told ``input_mode: stamps``: the estimator
    refuses the image, and the corner's reason is the mode (``frame_as_stamp``), its status
    naming the parameter and then the estimator's refusal."""
    p = params(input_mode="stamps")
    pipe = WavefrontPipeline(p.__getitem__, CORNERS)
    side = p["frame_min_side_px"]
    out = run_job(pipe.job_for(pair_of(pipe, "R00", side, value=50.0)))
    assert not out.valid and out.reason == "frame_as_stamp", out.status
    assert "(as a stamp: flat_or_empty: " in out.status, out.status
    assert (f"{side}x{side} images taken as one-donut stamps because input_mode is stamps: "
            "frames with several stars need input_mode frames") in out.status, out.status
    small = pipe.job_for(pair_of(pipe, "R04", 160))
    assert small.hint == ""
