"""The camera rotator's angle at a visit's stamp, from the stream of its joint states.

ROS-free: ofc_node feeds it the ``camera_rotator`` position of each ``JointState`` and asks for
the angle at each visit's stamp. The rotator holds still during an exposure and its position
is published at a few Hz or more, so the angle of the sample nearest to the stamp is the
visit's, provided that sample is within ``tolerance_s``; between two samples that bracket
the stamp the angle is interpolated linearly. A visit with no sample near enough gets no angle:
the controller refuses it rather than guess (a wrong angle mixes the corners' Zernikes).
"""

from __future__ import annotations

import bisect

import numpy as np

__all__ = ["MAX_RATE_DEG_S", "ROTATOR_JOINT", "RotatorHistory"]

#: Name of the camera rotator's joint in ``sensor_msgs/JointState`` (position in radians).
ROTATOR_JOINT = "camera_rotator"
#: No rotator turns further than one turn either way [rad].
MAX_ANGLE_RAD = 2.0 * np.pi
#: Faster than this between two samples is a slew (LSST's rotator turns at up to 3.5 deg/s):
#: an exposure is not taken then, and the angle is refused rather than interpolated.
MAX_RATE_DEG_S = 10.0


class RotatorHistory:
    """Bounded history of ``(stamp_ns, angle_deg)`` samples, kept in stamp order.

    Samples are inserted where their stamps put them, whatever order they arrive in: a
    sample stamped ahead of the others (a clock that is off, or another process on
    ``joint_states``) must not make the genuine samples that follow look old and be dropped.
    What a sample stamped ahead can still do is limited by the clock (``max_future_s`` of
    :meth:`add`) and by the lookup's checks: an angle that disagrees with its neighbours is a
    slew (:data:`MAX_RATE_DEG_S`) and two angles at one stamp are a contradiction; both refuse
    the visit rather than pick one.
    """

    def __init__(self, tolerance_s: float = 2.0, max_samples: int = 4096) -> None:
        self.tolerance_ns = int(tolerance_s * 1e9)
        self.max_samples = int(max_samples)
        self._stamps: list[int] = []
        self._angles: list[float] = []
        self._conflicts: set[int] = set()

    def __len__(self) -> int:
        return len(self._stamps)

    def clear(self) -> None:
        self._stamps.clear()
        self._angles.clear()
        self._conflicts.clear()

    def add(self, stamp_ns: int, angle_rad: float, now_ns: int | None = None,
            max_future_s: float | None = None) -> str | None:
        """Record a sample; returns why it was ignored (non-finite, beyond one turn, unset,
        ahead of ``now_ns`` by more than ``max_future_s``, older than every sample of a full
        history, or a second, different angle at a stamp already held: that stamp is then
        refused by :meth:`angle_deg`)."""
        if not np.isfinite(angle_rad):
            return f"non-finite rotator position {angle_rad!r}"
        if abs(angle_rad) > MAX_ANGLE_RAD:
            return (f"rotator position {angle_rad!r} rad is beyond +-{MAX_ANGLE_RAD:.4g} rad "
                    "(one turn either way): not a rotator angle")
        if stamp_ns <= 0:
            return "rotator sample with an unset stamp"
        if now_ns is not None and max_future_s is not None and \
                stamp_ns > now_ns + max_future_s * 1e9:
            return (f"rotator sample stamped {(stamp_ns - now_ns) / 1e9:.4g} s ahead of the "
                    f"clock (max_future_s {max_future_s:g})")
        angle_deg = float(np.rad2deg(angle_rad))
        i = bisect.bisect_left(self._stamps, stamp_ns)
        if i < len(self._stamps) and self._stamps[i] == stamp_ns:
            if abs(angle_deg - self._angles[i]) > 1e-9:
                self._conflicts.add(int(stamp_ns))
                return (f"two rotator angles at one stamp ({self._angles[i]:.6g} and "
                        f"{angle_deg:.6g} deg): a visit that needs it is refused")
            return None
        if i == 0 and len(self._stamps) >= self.max_samples:
            return (f"rotator sample at {stamp_ns} ns is older than every one of the "
                    f"{self.max_samples} kept")
        self._stamps.insert(i, int(stamp_ns))
        self._angles.insert(i, angle_deg)
        if len(self._stamps) > self.max_samples:
            self._conflicts.discard(self._stamps[0])
            del self._stamps[0], self._angles[0]
        return None

    def angle_deg(self, stamp_ns: int) -> tuple[float | None, str]:
        """The angle at ``stamp_ns`` [deg], or None with the reason."""
        if not self._stamps:
            return None, "no camera rotator angle received yet"
        stamps = self._stamps
        i = bisect.bisect_left(stamps, stamp_ns)
        if 0 < i < len(stamps) and stamps[i] - stamps[i - 1] <= 2 * self.tolerance_ns:
            t0, t1 = stamps[i - 1], stamps[i]
            a0, a1 = self._angles[i - 1], self._angles[i]
            rate = abs(a1 - a0) / ((t1 - t0) / 1e9)
            if rate > MAX_RATE_DEG_S:
                return None, (f"the camera rotator was slewing at the visit ({a0:.4g} -> "
                              f"{a1:.4g} deg in {(t1 - t0) / 1e9:.3g} s, {rate:.3g} deg/s > "
                              f"{MAX_RATE_DEG_S:g})")
            if t0 in self._conflicts or t1 in self._conflicts:
                return None, self._conflict(t0 if t0 in self._conflicts else t1)
            w = (stamp_ns - t0) / (t1 - t0)
            return a0 + w * (a1 - a0), "interpolated"
        near = min((j for j in (i - 1, i) if 0 <= j < len(stamps)),
                   key=lambda j: abs(stamps[j] - stamp_ns))
        gap = abs(stamps[near] - stamp_ns)
        if gap <= self.tolerance_ns:
            if stamps[near] in self._conflicts:
                return None, self._conflict(stamps[near])
            return self._angles[near], "nearest"
        return None, (f"no camera rotator angle within {self.tolerance_ns / 1e9:g} s of the "
                      f"visit (nearest sample {gap / 1e9:.3g} s away)")

    @staticmethod
    def _conflict(stamp_ns: int) -> str:
        return (f"two camera rotator angles were received for stamp {stamp_ns} ns: the angle "
                "at the visit is not known")
