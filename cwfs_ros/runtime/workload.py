"""What the corner workers cost, and whether a visit can finish within its timeout (no ROS).

wavefront_node runs each corner's job on the worker the corner is assigned to
(:class:`cwfs_ros.runtime.corner_pool.CornerPool`); a worker runs its corners one after the
other. So a visit is complete when the busiest worker has run all its corners: the
**visit-timeout promise** holds while, for every worker, the sum of its corners' recent
per-visit cost (90th percentile of ``compute_ms``) plus what is already queued fits in
``visit_timeout_s``. :class:`WorkloadMonitor` keeps those figures, the workers' cache counts
(hit rates of the field tiles and pair geometries) and proposes a cost-balanced assignment.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from cwfs_ros.errors import Problem

__all__ = ["WorkloadMonitor", "balanced_affinity"]

# A new assignment is taken only when it lowers the busiest worker's load by this share:
# corners move rarely, as a moved corner's tiles must be built on its new worker first.
REBALANCE_GAIN = 0.2
# Visits per corner before its cost is trusted for the promise and the assignment.
MIN_SAMPLES = 3


def balanced_affinity(costs: Mapping[str, float], n_workers: int) -> dict[str, int]:
    """Corners to workers by cost, largest first onto the least-loaded worker (LPT);
    ties go to the lower worker and corner names break cost ties, so the result is stable."""
    load = [0.0] * max(1, int(n_workers))
    out: dict[str, int] = {}
    for corner in sorted(costs, key=lambda c: (-costs[c], c)):
        i = min(range(len(load)), key=lambda k: (load[k], k))
        out[corner] = i
        load[i] += costs[corner]
    return out


def _loads(costs: Mapping[str, float], affinity: Mapping[str, int]) -> dict[int, float]:
    out: dict[int, float] = {}
    for corner, i in affinity.items():
        out[i] = out.get(i, 0.0) + costs.get(corner, 0.0)
    return out


@dataclass
class WorkloadMonitor:
    """Recent per-corner costs and the workers' cache counts.

    Args:
        history: visits kept per corner.
    """

    history: int = 20
    _cost_ms: dict[str, deque] = field(default_factory=dict)
    _caches: dict[int, dict[str, tuple[int, int, int, int]]] = field(default_factory=dict)
    _warm_caches: dict[int, dict[str, tuple[int, int, int, int]]] = field(default_factory=dict)

    def record(self, corner: str, compute_ms: float, worker_pid: int,
               caches: Mapping[str, tuple[int, int, int, int]] | None) -> None:
        """One finished corner job (its wall time in the worker, and the worker's caches)."""
        if math.isfinite(compute_ms) and compute_ms > 0:
            self._cost_ms.setdefault(corner, deque(maxlen=self.history)).append(compute_ms)
        if caches:
            self._caches[int(worker_pid)] = dict(caches)

    def record_warm(self, worker_pid: int,
                    caches: Mapping[str, tuple[int, int, int, int]] | None) -> None:
        """A worker's caches at the end of its warm-up (builds after it are counted apart)."""
        if caches:
            self._warm_caches[int(worker_pid)] = dict(caches)
            self._caches[int(worker_pid)] = dict(caches)

    def forget_workers(self) -> None:
        """The workers were replaced (cleanup, re-warm): their counts start again."""
        self._caches.clear()
        self._warm_caches.clear()

    def cost_s(self, corner: str) -> float:
        """90th percentile of the corner's recent job times [s]; NaN before MIN_SAMPLES."""
        v = self._cost_ms.get(corner)
        if not v or len(v) < MIN_SAMPLES:
            return float("nan")
        return float(np.percentile(np.asarray(v), 90)) / 1e3

    def costs_s(self, corners: Iterable[str]) -> dict[str, float]:
        """:meth:`cost_s` of each corner that has one."""
        out = {c: self.cost_s(c) for c in corners}
        return {c: v for c, v in out.items() if math.isfinite(v)}

    def promise(self, affinity: Mapping[str, int], queued: Mapping[int, int],
                timeout_s: float) -> tuple[Problem | None, float]:
        """(a ``visit_timeout`` problem if the busiest worker cannot finish a visit in time,
        the predicted time of a visit [s]: the busiest worker's corners, at their p90 cost,
        behind the jobs it has queued beyond one visit's)."""
        costs = self.costs_s(affinity)
        if len(costs) < len(affinity):
            return None, float("nan")
        loads = _loads(costs, affinity)
        served = {i: list(affinity.values()).count(i) for i in loads}
        # Jobs queued beyond one visit's wait ahead of it, at the worker's mean corner cost.
        need_s = {i: loads[i] * (1 + max(0, int(queued.get(i, 0)) - served[i]) / served[i])
                  for i in loads}
        worst = max(need_s, key=need_s.__getitem__)
        need = need_s[worst]
        if need <= timeout_s:
            return None, need
        corners = "+".join(sorted(c for c, a in affinity.items() if a == worst))
        return Problem("visit_timeout", (
            f"worker {worst} ({corners}) needs {need:.2f} s for a visit (p90 "
            + ", ".join(f"{c} {costs[c]:.2f} s" for c in sorted(costs) if affinity[c] == worst)
            + f"; {queued.get(worst, 0)} job(s) queued) > visit_timeout_s {timeout_s:g} s: "
            "visits will be published with corners missing; raise visit_timeout_s or "
            "workers, or send fewer stars")), need

    def proposal(self, affinity: Mapping[str, int], n_workers: int) -> dict[str, int] | None:
        """A cost-balanced assignment, if it lowers the busiest worker's p90 load by at least
        REBALANCE_GAIN; else None (every corner needs MIN_SAMPLES visits first)."""
        costs = self.costs_s(affinity)
        if len(costs) < len(affinity) or n_workers < 2:
            return None
        new = balanced_affinity(costs, n_workers)
        now, then = max(_loads(costs, affinity).values()), max(_loads(costs, new).values())
        return new if then <= (1.0 - REBALANCE_GAIN) * now else None

    def cache_values(self) -> list[tuple[str, str]]:
        """``cache.<kind>`` diagnostics over all workers: the hit rate of the requests since
        the warm-up (what a running node sees), what the warm-up built, and the entries held
        against the cache size."""
        kinds = sorted({k for c in self._caches.values() for k in c})
        out = []
        for kind in kinds:
            now = [c[kind] for c in self._caches.values() if kind in c]
            warm = [w[kind] for w in self._warm_caches.values() if kind in w]
            hits = sum(v[0] for v in now) - sum(v[0] for v in warm)
            builds = sum(v[1] for v in now) - sum(v[1] for v in warm)
            rate = f"{100.0 * hits / (hits + builds):.1f} %" if hits + builds else "-"
            out.append((f"cache.{kind}",
                        f"hit {rate} after warm-up ({hits} hits, {builds} builds; "
                        f"{sum(v[1] for v in warm)} built at warm-up); held "
                        f"{sum(v[2] for v in now)} in {len(now)} worker(s), "
                        f"size {max(v[3] for v in now)} each"))
        return out
