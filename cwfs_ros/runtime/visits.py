"""Visit bookkeeping for the wavefront node: image pairing and 76-vector assembly (no ROS).

Two small state machines, driven by the node with explicit ``now`` times (monotonic seconds)
so that they can be tested without a clock or a middleware:

* :class:`PairingBuffer` pairs the intra- and extra-focal images of each corner by their
  exposure stamp (integer nanoseconds, equal within a tolerance). It reports duplicate, late,
  conflicting and (after a timeout) unpaired images as :class:`Rejection` records.
* :func:`image_record_from_msg` decodes a ``sensor_msgs/Image``-shaped object (an rclpy
  message, or one deserialised from a bag by rosbags: both carry the same field names) into an
  :class:`ImageRecord`, so the live node and the offline replay decode identically.
* :class:`VisitAssembler` collects the per-corner results of a visit (from this process or
  from ``CornerWavefront`` messages of other processes) into the fixed 76-entry layout of
  ``cwfs_msgs/WavefrontVector``: 4 corners (R00, R04, R40, R44) x Noll Z4..Z22. A visit is
  emitted when all four corners are in, or when the timeout expires, with the missing corners
  marked invalid.

Visit identity: a visit is a stamp. A later record whose stamp is within ``tolerance_ns`` of a
pending or recently closed visit's stamp belongs to that visit.

One exposure, one stamp: two images of the same corner, side and visit are *the same* when
their messages are byte-identical in the fields that make the picture (encoding, height,
width, step, is_bigendian and every data byte: :attr:`ImageRecord.digest`); a re-sent copy is
a ``duplicate`` and ignored. Anything else is ``conflicting_images``: two exposures claim one
stamp, and nothing can tell which of them the partner image belongs to, so the corner's visit
is invalid, never a pair. A conflict found while the first image waits for its partner closes
the corner's visit at once; one found after the pair was formed is reported by
:meth:`PairingBuffer.add` and the node invalidates the corner's result (before it is published,
or in the :class:`VisitAssembler` with :meth:`VisitAssembler.invalidate` until the visit is
emitted).
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from cwfs_ros.layout import CLOCK_RESET_S, CORNERS, N_ZK, NOLL, SIDES
from cwfs_ros.runtime.images import decode_image, inspect_pixels

__all__ = [
    "CornerEntry",
    "ImageRecord",
    "PairReady",
    "PairingBuffer",
    "Rejection",
    "VisitAssembler",
    "VisitVector",
    "corner_entry_from_outcome",
    "format_stamp",
    "image_record_from_msg",
    "load_corner_fields",
    "message_digest",
    "stamp_to_ns",
    "zernikes_by_noll",
]



def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ``builtin_interfaces/Time``-shaped object (``sec``, ``nanosec``)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def format_stamp(stamp_ns: int) -> str:
    """``sec.nanosec`` text of a stamp, for messages."""
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return f"{sec}.{nsec:09d}"


@dataclass(frozen=True)
class Rejection:
    """Something the node did not use, and why.

    Attributes:
        reason: short tag for counting (``duplicate``, ``late``, ``unpaired``,
            ``unknown_corner``, ``unknown_side``, ``bad_corner_wavefront``,
            ``corner_mismatch`` (a remote corner's message naming another corner), a refusal
            before decoding (``bad_stamp``, ``no_stamp``, ``future_stamp``, ``too_large``,
            ``frame_mismatch``, ``untrusted_source``: :meth:`WavefrontPipeline.refusal
            <cwfs_ros.runtime.pipeline.WavefrontPipeline.refusal>` and wavefront_node), or a
            decoding / estimator tag such as ``unsupported_encoding``).
        message: one human-readable sentence.
    """

    reason: str
    message: str
    corner: str = ""
    side: str = ""
    stamp_ns: int = 0


@dataclass
class ImageRecord:
    """One received image, decoded or not.

    Attributes:
        image: the decoded stamp (``None`` when decoding failed).
        error: ``None``, or the ``"<reason>: <explanation>"`` text of a decoding failure; the
            pair is still formed so that the corner's result can say what was wrong.
        reason: the decoding failure's tag (:class:`~cwfs_ros.runtime.images.ImageDecodeError`
            ``reason``), ``""`` when decoded.
        received: monotonic receive time in seconds.
        digest: identity of the picture (see the module docstring: equal digests, same
            picture); empty when not computed, then the decoded pixels decide.
        encoding: the message's encoding.
        full_scale_px: integer pixels at the top of their type's range, when the decoder was
            told to count rather than refuse them (:func:`image_record_from_msg`): in a
            frame they make only their own star saturated.
    """

    corner: str
    side: str
    stamp_ns: int
    image: np.ndarray | None = None
    error: str | None = None
    reason: str = ""
    frame_id: str = ""
    received: float = 0.0
    digest: bytes = b""
    encoding: str = ""
    full_scale_px: int = 0

    def identity(self) -> bytes:
        """:attr:`digest`, or one of the decoded pixels (or the error) when it is unset."""
        if self.digest:
            return self.digest
        h = _digest()
        if self.image is not None:
            a = np.ascontiguousarray(self.image)
            h.update(repr((a.shape, a.dtype.str)).encode())
            h.update(a.tobytes())
        else:
            h.update(str(self.error).encode())
        return h.digest()[:_DIGEST_BYTES]


# An image's identity decides duplicate against conflicting_images, so it must not collide by
# accident; SHA-256 (cut to 16 bytes) is the fastest such hash in the standard library where
# the CPU has SHA instructions, as x86 machines of the last years do: 18 ms for a 32 MB
# whole half-chip against BLAKE2b's 38 (bench/bench_image_ingest.py), eight frames a visit.
_DIGEST_BYTES = 16


def _digest() -> Any:
    return hashlib.sha256()


def message_digest(msg: Any) -> bytes:
    """Identity of an Image message's picture: encoding, size, layout and data bytes."""
    h = _digest()
    h.update(repr((str(msg.encoding), int(msg.height), int(msg.width), int(msg.step),
                   bool(msg.is_bigendian))).encode())
    data = msg.data
    try:
        h.update(memoryview(data))
    except TypeError:
        h.update(bytes(bytearray(data)))
    return h.digest()[:_DIGEST_BYTES]


def image_record_from_msg(msg: Any, corner: str, side: str, received: float, *,
                          full_scale_ok: bool = False) -> ImageRecord:
    """Decode a ``sensor_msgs/Image``-shaped message into an :class:`ImageRecord` (never raises).

    ``msg`` is anything with the Image fields (``header.stamp``, ``header.frame_id``,
    ``height``, ``width``, ``encoding``, ``step``, ``is_bigendian``, ``data``): an rclpy message
    or a rosbags-deserialised one. ``received`` is the receive time in seconds (monotonic for
    the live node, the bag's receive stamp for a replay). A message that cannot be decoded gives
    a record with ``image=None`` and ``error`` naming the problem; it still takes part in
    pairing so that the corner's result reports it. Integer pixels at full scale refuse the
    image ``saturated`` (a stamp), or with ``full_scale_ok`` are counted in
    :attr:`ImageRecord.full_scale_px` (a frame: its detection judges each star).
    """
    rec = ImageRecord(corner, side, stamp_to_ns(msg.header.stamp),
                      frame_id=str(msg.header.frame_id), received=float(received))
    try:
        rec.digest = message_digest(msg)
        rec.encoding = str(msg.encoding)
        image = decode_image(msg.data, height=msg.height, width=msg.width,
                             encoding=msg.encoding, step=msg.step,
                             is_bigendian=bool(msg.is_bigendian))
        rec.full_scale_px = inspect_pixels(image, rec.encoding, full_scale_ok=full_scale_ok)
        rec.image = image
    except ValueError as exc:  # ImageDecodeError is a ValueError
        rec.error, rec.reason = str(exc), str(getattr(exc, "reason", "bad_data"))
    except Exception as exc:  # noqa: BLE001 - a message must never crash the caller
        rec.error, rec.reason = f"bad_data: {type(exc).__name__}: {exc}", "bad_data"
    return rec


@dataclass(frozen=True)
class PairReady:
    """An intra/extra pair of one corner and one visit, ready for estimation.

    ``stamp_ns`` is the intra image's stamp (the visit's stamp; the extra's is within the
    tolerance). ``error`` is set when either image failed to decode.
    """

    corner: str
    stamp_ns: int
    intra: ImageRecord
    extra: ImageRecord

    @property
    def error(self) -> str | None:
        """What is wrong with the pair's images, each named by side: ``"intra image:
        <explanation>"``, with the image's own reason tag where it is not the pair's
        :attr:`reason` (which the outcome's status leads with)."""
        lead = self.intra.reason or self.extra.reason  # the pair's reason (not via .reason)
        errs = []
        for r in (self.intra, self.extra):
            if r.error:
                text = r.error
                if r.reason and r.reason == lead and text.startswith(r.reason + ": "):
                    text = text[len(r.reason) + 2:]
                errs.append(f"{r.side} image: {text}")
        return "; ".join(errs) if errs else None

    @property
    def reason(self) -> str:
        """The tag of the first undecodable image of the pair (``""`` when both decoded)."""
        return self.intra.reason or self.extra.reason or ("bad_image" if self.error else "")


class _Closed:
    """Bounded memory of closed visit stamps and why they were closed."""

    def __init__(self, capacity: int) -> None:
        self.capacity = max(1, int(capacity))
        self._items: OrderedDict[int, str] = OrderedDict()

    def add(self, stamp_ns: int, how: str) -> None:
        self._items[int(stamp_ns)] = how
        self._items.move_to_end(int(stamp_ns))
        while len(self._items) > self.capacity:
            self._items.popitem(last=False)

    def find(self, stamp_ns: int, tol: int) -> str | None:
        how = self._items.get(int(stamp_ns))
        if how is not None or tol <= 0:
            return how
        for s, h in self._items.items():
            if abs(s - stamp_ns) <= tol:
                return h
        return None

    def oldest(self) -> int | None:
        """The oldest stamp still remembered, once the memory is full (else None)."""
        if len(self._items) < self.capacity:
            return None
        return min(self._items)

    def age_check(self, t: int, tol: int, reset_ns: int, where: str, corner: str,
                  side: str) -> Rejection | None:
        """None for a stamp within the visits remembered. For one older than all of them: a
        ``late`` rejection, or, when it is also more than ``reset_ns`` behind the newest, a
        ``clock_jump`` notice, the history cleared and the stamp to be taken: the source's
        clock went back (a restarted camera or simulator, a corrected clock), and refusing
        it as late would refuse every later visit too, until its stamps caught up."""
        oldest = self.oldest()
        if oldest is None or t >= oldest - tol:
            return None
        behind = max(self._items) - t
        if behind <= reset_ns:
            return Rejection("late", f"{where}: older than every visit still tracked",
                             corner, side, t)
        self._items.clear()
        return Rejection("clock_jump", f"{where}: {behind / 1e9:.0f} s before the newest "
                         "visit: the source's clock went back; the visit history is cleared "
                         "and its images are taken again", corner, side, t)



class PairingBuffer:
    """Pairs intra and extra images per corner by stamp.

    Args:
        corners: corners served (others are rejected as ``unknown_corner``).
        tolerance_ns: two stamps within this many ns belong to the same visit.
        timeout_s: an image waits at most this long (receive time) for its partner; then it is
            dropped and reported ``unpaired`` by :meth:`expire`.
        history: closed visits remembered per corner (for duplicate / late detection).
    """

    def __init__(self, corners: Sequence[str] = CORNERS, *, tolerance_ns: int = 1_000_000,
                 timeout_s: float = 2.0, history: int = 256,
                 clock_reset_s: float = CLOCK_RESET_S) -> None:
        self.corners = tuple(corners)
        self.tolerance_ns = int(tolerance_ns)
        self.timeout_s = float(timeout_s)
        self.clock_reset_ns = int(clock_reset_s * 1e9)
        self._pending: dict[str, dict[str, list[ImageRecord]]] = {
            c: {s: [] for s in SIDES} for c in self.corners}
        self._closed = {c: _Closed(history) for c in self.corners}
        # Identities of the images of the visits paired last, per corner: {stamp: {side: id}}.
        self._paired: dict[str, OrderedDict[int, dict[str, bytes]]] = {
            c: OrderedDict() for c in self.corners}
        self._history = max(1, int(history))

    def pending_count(self) -> int:
        return sum(len(v) for sides in self._pending.values() for v in sides.values())

    def add(self, rec: ImageRecord) -> tuple[PairReady | None, Rejection | None]:
        """Add one image; return the completed pair (or None) and why the image was not kept
        (or None), or a ``clock_jump`` notice when it was kept after its source's clock went
        back."""
        c, side, t = rec.corner, rec.side, int(rec.stamp_ns)
        where = f"{side} image of {c} at stamp {format_stamp(t)}"
        if c not in self._pending:
            return None, Rejection("unknown_corner", f"{where}: corner not served here "
                                   f"(serving {', '.join(self.corners)})", c, side, t)
        if side not in SIDES:
            return None, Rejection("unknown_side", f"{where}: side must be intra or extra",
                                   c, side, t)
        problem = self._closed_visit_problem(rec, where)
        if problem is not None:
            return None, problem
        notice = self._closed[c].age_check(t, self.tolerance_ns, self.clock_reset_ns, where,
                                           c, side)
        if notice is not None and notice.reason == "late":
            return None, notice
        problem = self._waiting_problem(rec, where)
        if problem is not None:
            return None, problem
        return self._pair_or_wait(rec), notice

    def _closed_visit_problem(self, rec: ImageRecord, where: str) -> Rejection | None:
        """Why an image of a visit already closed is not taken (``conflicting_images`` when
        it is not the image that was paired, ``duplicate`` when it is, ``late`` for a visit
        closed otherwise), or None for an open visit."""
        c, side, t = rec.corner, rec.side, int(rec.stamp_ns)
        closed = self._closed[c].find(t, self.tolerance_ns)
        if closed == "paired":
            found = self._paired_lookup(c, t)
            if found is not None and found[1][side] != rec.identity():
                # Reported under the visit's stamp (the pair's), which its outputs carry.
                return Rejection(
                    "conflicting_images", f"{where}: a different {side} image of that visit "
                    "was already paired: two exposures claim one stamp; the corner's visit is "
                    "invalid", c, side, found[0])
            return Rejection("duplicate", f"{where}: that visit was already paired",
                             c, side, t)
        if closed is not None:
            return Rejection("late", f"{where}: arrived after that visit was closed "
                             f"({closed})", c, side, t)
        return None

    def _waiting_problem(self, rec: ImageRecord, where: str) -> Rejection | None:
        """Why an image is not taken when one of its side and visit already waits: another
        exposure under the same stamp (both dropped, the visit closed) or the same image
        again; None when none waits."""
        c, side, t = rec.corner, rec.side, int(rec.stamp_ns)
        same = self._pending[c][side]
        waiting = [r for r in same if abs(r.stamp_ns - t) <= self.tolerance_ns]
        if not waiting:
            return None
        if any(r.identity() != rec.identity() for r in waiting):
            # Neither image can be paired: drop the waiting one and close the visit.
            for r in waiting:
                same.remove(r)
            visit = waiting[0].stamp_ns  # the visit's stamp, which its outputs carry
            self._closed[c].add(visit, "conflicting_images")
            return Rejection(
                "conflicting_images", f"{where}: a different {side} image of that visit is "
                "already waiting: two exposures claim one stamp; the corner's visit is "
                "invalid", c, side, visit)
        return Rejection("duplicate", f"{where}: an image of this side and visit is "
                         "already waiting for its partner", c, side, t)

    def _pair_or_wait(self, rec: ImageRecord) -> PairReady | None:
        """The pair ``rec`` completes with the nearest-stamped image of the other side
        within the tolerance (the visit then closed as paired), or None, ``rec`` waiting."""
        c, side, t = rec.corner, rec.side, int(rec.stamp_ns)
        others = self._pending[c]["extra" if side == "intra" else "intra"]
        near = [r for r in others if abs(r.stamp_ns - t) <= self.tolerance_ns]
        if not near:
            self._pending[c][side].append(rec)
            return None
        match = min(near, key=lambda r: abs(r.stamp_ns - t))
        others.remove(match)
        intra, extra = (rec, match) if side == "intra" else (match, rec)
        self._closed[c].add(intra.stamp_ns, "paired")
        paired = self._paired[c]
        paired[intra.stamp_ns] = {"intra": intra.identity(), "extra": extra.identity()}
        while len(paired) > self._history:
            paired.popitem(last=False)
        return PairReady(c, intra.stamp_ns, intra, extra)

    def why_missing(self, corner: str, stamp_ns: int) -> str:
        """What became of a corner's images of a visit, for a visit published without it:
        paired (its estimate had not come back), one half waiting for the other, or none
        received."""
        if corner not in self._pending:
            return "not served here"
        if self.was_paired(corner, stamp_ns):
            return "its images were paired, but its estimate had not come back"
        waiting = [side for side in SIDES if any(abs(r.stamp_ns - stamp_ns) <= self.tolerance_ns
                                                 for r in self._pending[corner][side])]
        if waiting:
            other = [side for side in SIDES if side not in waiting]
            return f"its {waiting[0]} image came, its {other[0]} image had not"
        return "none of its images had come"

    def was_paired(self, corner: str, stamp_ns: int) -> bool:
        """Whether that corner's visit was paired (still remembered)."""
        return corner in self._paired and self._paired_lookup(corner, stamp_ns) is not None

    def _paired_lookup(self, corner: str, stamp_ns: int) -> tuple[int, dict[str, bytes]] | None:
        """(the paired visit's stamp, its images' identities) within the tolerance, or None."""
        paired = self._paired[corner]
        if stamp_ns in paired:
            return stamp_ns, paired[stamp_ns]
        for s, ids in paired.items():
            if abs(s - stamp_ns) <= self.tolerance_ns:
                return s, ids
        return None

    def pending_bytes(self) -> int:
        """Bytes held by the decoded images waiting for their partners."""
        return sum(r.image.nbytes for sides in self._pending.values()
                   for v in sides.values() for r in v if r.image is not None)

    def drop_oldest(self) -> Rejection | None:
        """Drop the image that has waited longest (its visit closes), to bound memory."""
        oldest = None
        for sides in self._pending.values():
            for v in sides.values():
                for r in v:
                    if oldest is None or r.received < oldest.received:
                        oldest = r
        if oldest is None:
            return None
        self._pending[oldest.corner][oldest.side].remove(oldest)
        self._closed[oldest.corner].add(oldest.stamp_ns, "dropped: memory limit")
        other = "extra" if oldest.side == "intra" else "intra"
        return Rejection("memory_limit", f"{oldest.side} image of {oldest.corner} at stamp "
                         f"{format_stamp(oldest.stamp_ns)} dropped before its {other} image "
                         "came: pending images reached the memory limit (oldest first)",
                         oldest.corner, oldest.side, oldest.stamp_ns)

    def close(self, corner: str, stamp_ns: int, how: str) -> list[Rejection]:
        """Close a visit of a corner from outside (e.g. the assembler timed it out).

        Images of that visit still waiting are dropped (reported ``unpaired``) and later ones
        are rejected as ``late``.
        """
        if corner not in self._pending:
            return []
        out = []
        for side in SIDES:
            keep = []
            for r in self._pending[corner][side]:
                if abs(r.stamp_ns - stamp_ns) <= self.tolerance_ns:
                    out.append(self._unpaired(r, how))
                else:
                    keep.append(r)
            self._pending[corner][side] = keep
        if self._closed[corner].find(stamp_ns, self.tolerance_ns) is None:
            self._closed[corner].add(stamp_ns, how)
        return out

    def _unpaired(self, r: ImageRecord, how: str) -> Rejection:
        other = "extra" if r.side == "intra" else "intra"
        return Rejection("unpaired", f"{r.side} image of {r.corner} at stamp "
                         f"{format_stamp(r.stamp_ns)} got no {other} image ({how})",
                         r.corner, r.side, r.stamp_ns)

    def expire(self, now: float) -> list[Rejection]:
        """Drop images that waited longer than the timeout; their visits become closed."""
        out = []
        for c, sides in self._pending.items():
            for side in SIDES:
                keep = []
                for r in sides[side]:
                    if now - r.received > self.timeout_s:
                        how = f"timeout {self.timeout_s:g} s"
                        out.append(self._unpaired(r, how))
                        self._closed[c].add(r.stamp_ns, f"unpaired after {how}")
                    else:
                        keep.append(r)
                sides[side] = keep
        return out


@dataclass(frozen=True)
class CornerEntry:
    """One corner's result for one visit, as the assembler consumes it.

    Attributes:
        zernikes_nm: Z4..Z22 (19 values, nm) when ``valid``; ignored otherwise.
        uncertainty_nm: (19,) one-sigma per term (nm), or None when not reported.
        n_pairs: donut pairs behind the estimate (0: not reported or none).
    """

    corner: str
    stamp_ns: int
    zernikes_nm: np.ndarray | None
    valid: bool
    status: str
    uncertainty_nm: np.ndarray | None = None
    n_pairs: int = 0


@dataclass(frozen=True)
class VisitVector:
    """The assembled visit (the content of a ``WavefrontVector``).

    Attributes:
        zernikes_nm: (76,) corner-major Z4..Z22; NaN for invalid or missing corners.
        corner_valid: (4,) validity in :data:`CORNERS` order.
        statuses: per-corner status text (``"ok"``, the corner's reason, or ``"missing"``).
        status: ``"ok"`` when every corner is valid, else a summary naming the bad corners.
        complete: all four corners reported before the timeout.
        uncertainty_nm: (76,) one-sigma per term of the valid corners (nm); 0 = not reported
            (the ``WavefrontVector`` convention).
        n_pairs: (4,) donut pairs behind each valid corner (0: not reported, or invalid).
    """

    stamp_ns: int
    zernikes_nm: np.ndarray
    corner_valid: tuple[bool, ...]
    statuses: tuple[str, ...]
    status: str
    complete: bool
    corners: tuple[str, ...] = CORNERS
    uncertainty_nm: np.ndarray = field(default_factory=lambda: np.zeros(len(CORNERS) * N_ZK))
    n_pairs: tuple[int, ...] = (0,) * len(CORNERS)


@dataclass
class _Visit:
    stamp_ns: int
    started: float
    entries: dict[str, CornerEntry] = field(default_factory=dict)


class VisitAssembler:
    """Collects per-corner results into the 76-vector of a visit.

    Args:
        tolerance_ns: corner stamps within this many ns belong to the same visit.
        timeout_s: a visit is emitted this long after its first corner arrived, with the
            corners still missing marked invalid.
        history: emitted visits remembered (for duplicate / late detection).
    """

    def __init__(self, *, tolerance_ns: int = 1_000_000, timeout_s: float = 2.0,
                 history: int = 256, clock_reset_s: float = CLOCK_RESET_S) -> None:
        self.tolerance_ns = int(tolerance_ns)
        self.timeout_s = float(timeout_s)
        self.clock_reset_ns = int(clock_reset_s * 1e9)
        self._visits: list[_Visit] = []
        self._closed = _Closed(history)

    def pending_count(self) -> int:
        return len(self._visits)

    def _find(self, stamp_ns: int) -> _Visit | None:
        best = None
        for v in self._visits:
            d = abs(v.stamp_ns - stamp_ns)
            if d <= self.tolerance_ns and (best is None or d < abs(best.stamp_ns - stamp_ns)):
                best = v
        return best

    def add(self, entry: CornerEntry, now: float) -> tuple[VisitVector | None,
                                                            Rejection | None]:
        """Add a corner result; return the visit if it is now complete, and why the result
        was not kept (or a ``clock_jump`` notice when it was, after its clock went back)."""
        c, t = entry.corner, int(entry.stamp_ns)
        where = f"wavefront of {c} at stamp {format_stamp(t)}"
        if c not in CORNERS:
            return None, Rejection("unknown_corner", f"{where}: corner must be one of "
                                   f"{', '.join(CORNERS)}", c, "", t)
        entry = checked_entry(entry)
        closed = self._closed.find(t, self.tolerance_ns)
        if closed is not None:
            return None, Rejection("late", f"{where}: arrived after the visit was published "
                                   f"({closed})", c, "", t)
        notice = self._closed.age_check(t, self.tolerance_ns, self.clock_reset_ns, where, c,
                                        "")
        if notice is not None and notice.reason == "late":
            return None, notice
        visit = self._find(t)
        if visit is None:
            visit = _Visit(t, now)
            self._visits.append(visit)
        elif c in visit.entries:
            return None, Rejection("duplicate", f"{where}: this corner already reported for "
                                   "the visit", c, "", t)
        visit.entries[c] = entry
        if len(visit.entries) == len(CORNERS):
            return self._emit(visit, complete=True), notice
        return None, notice

    def invalidate(self, corner: str, stamp_ns: int, status: str) -> tuple[bool,
                                                                          VisitVector | None]:
        """Mark a corner of a pending visit invalid (``status`` says why), whether its
        result is in or still to come (a later result is then refused as a duplicate).

        Returns (done, the visit if it is now complete); done is False when the visit was
        already emitted or has no corner in yet."""
        t = int(stamp_ns)
        if corner not in CORNERS or self._closed.find(t, self.tolerance_ns) is not None:
            return False, None
        visit = self._find(t)
        if visit is None:
            return False, None
        visit.entries[corner] = CornerEntry(corner, t, None, False, status)
        if len(visit.entries) == len(CORNERS):
            return True, self._emit(visit, complete=True)
        return True, None

    def expire(self, now: float, why_missing: Callable[[str, int], str] | None = None
               ) -> list[VisitVector]:
        """Emit every visit older than the timeout, missing corners marked invalid (with
        ``why_missing(corner, stamp_ns)`` in their status, e.g.
        :meth:`PairingBuffer.why_missing`)."""
        due = [v for v in self._visits if now - v.started > self.timeout_s]
        return [self._emit(v, complete=False, why_missing=why_missing)
                for v in sorted(due, key=lambda v: v.stamp_ns)]

    def _emit(self, visit: _Visit, *, complete: bool,
              why_missing: Callable[[str, int], str] | None = None) -> VisitVector:
        self._visits.remove(visit)
        z = np.full(len(CORNERS) * N_ZK, np.nan)
        unc = np.zeros(len(CORNERS) * N_ZK)
        pairs = [0] * len(CORNERS)
        valid, statuses, bad = [], [], []
        for i, c in enumerate(CORNERS):
            e = visit.entries.get(c)
            if e is None:
                st = f"missing: no wavefront within the {self.timeout_s:g} s visit timeout"
                if why_missing is not None:
                    st += f" ({why_missing(c, visit.stamp_ns)})"
                ok = False
            else:
                ok, st = e.valid, e.status if not e.valid else "ok"
                if ok:
                    z[i * N_ZK:(i + 1) * N_ZK] = e.zernikes_nm
                    unc[i * N_ZK:(i + 1) * N_ZK] = _reported(e.uncertainty_nm)
                    pairs[i] = max(0, min(int(e.n_pairs), 65535))
            valid.append(ok)
            statuses.append(st)
            if not ok:
                bad.append(f"{c} {st}")
        how = "complete" if complete else f"timeout {self.timeout_s:g} s"
        self._closed.add(visit.stamp_ns, f"published, {how}")
        status = "ok" if not bad else "invalid corners: " + "; ".join(bad)
        return VisitVector(visit.stamp_ns, z, tuple(valid), tuple(statuses), status, complete,
                           uncertainty_nm=unc, n_pairs=tuple(pairs))


def corner_entry_from_outcome(out: Any) -> CornerEntry:
    """The assembly entry of a corner job's outcome, as wavefront_node and the offline replay
    both build it (so that a replayed vector carries what the live one did)."""
    return CornerEntry(out.corner, out.stamp_ns, out.zernikes_nm, out.valid, out.status,
                       out.uncertainty_nm, out.n_pairs if out.valid else 0)


def _reported(u: np.ndarray | None) -> np.ndarray:
    """(19,) uncertainty as a WavefrontVector carries it: NaN, negative or absent -> 0."""
    if u is None:
        return np.zeros(N_ZK)
    a = np.asarray(u, dtype=np.float64).reshape(-1)
    if a.shape != (N_ZK,):
        return np.zeros(N_ZK)
    return np.where(np.isfinite(a) & (a > 0), a, 0.0)


def checked_entry(e: CornerEntry) -> CornerEntry:
    """A valid entry must carry 19 finite Zernikes; otherwise it is treated as invalid."""
    if not e.valid:
        return e
    z = None if e.zernikes_nm is None else np.asarray(e.zernikes_nm, dtype=np.float64)
    if z is None or z.shape != (N_ZK,):
        shape = None if z is None else z.shape
        return CornerEntry(e.corner, e.stamp_ns, None, False,
                           f"bad_corner_wavefront: flagged valid but holds {shape} Zernikes "
                           f"instead of Z4..Z22 ({N_ZK})")
    if not np.all(np.isfinite(z)):
        return CornerEntry(e.corner, e.stamp_ns, None, False,
                           "bad_corner_wavefront: flagged valid but holds NaN/Inf Zernikes")
    return CornerEntry(e.corner, e.stamp_ns, z, True, e.status, e.uncertainty_nm, e.n_pairs)


def zernikes_by_noll(noll: Iterable[int], values: Iterable[float]) -> np.ndarray | None:
    """Z4..Z22 (19 values) from parallel ``noll`` / ``values`` lists, or None if incomplete."""
    noll, values = list(noll), list(values)
    if len(noll) != len(values):
        return None
    table = {int(j): float(v) for j, v in zip(noll, values, strict=True)}
    if any(j not in table for j in NOLL):
        return None
    return np.array([table[j] for j in NOLL])


def load_corner_fields(path: str | None = None) -> dict[str, dict[str, tuple[float, float]]]:
    """Field points of each corner's half-chips: ``{corner: {"intra": (x, y), "extra": ...}}``.

    Read from ``config/sensors/lsst_corners.yaml`` (or ``path``); degrees, batoid field frame.
    The image centre of each half-sensor stamp is taken to be at that field point.
    """
    from cwfs_ros.config import load_sensor_geometry

    return {name: {side: g.field_deg(side) for side in SIDES}
            for name, g in load_sensor_geometry(path).items()}
