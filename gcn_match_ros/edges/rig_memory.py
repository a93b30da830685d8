"""Two-view models that outlive a window: the cameras of one rig keep their relative pose.

:class:`RigMemory` keeps, per camera pair, the last trusted model that
:func:`.candidates.candidate_edges` fitted. For the next window of the same pair the model is
first re-checked on that window's seeds (the confident descriptor pairs a fit would use,
:meth:`.verify.PairModel.rechecked`): it is reused — no RANSAC — when it is still trusted
(:meth:`.verify.PairModel.trusted`) and explains at least :data:`REUSE_SHARE` of the inlier
share it had when fitted. Otherwise it is dropped and the pair re-fitted, so a camera pair
whose geometry changes (cameras on different robots, a rig knocked out of alignment) is
re-fitted in every window and never matched with a stale model.

A camera pair whose fit gives no trusted model — cameras that point different ways and share
no scene — backs off: after k failed fits in a row it is not fitted for the next
min(2ᵏ − 1, :data:`MAX_SKIPPED`) windows (1, 3, 7, 7, ...) and has no model there, as it would
have after another failed fit. A failed fit runs RANSAC to its last iteration (~27 ms a pair
on the generated 4-camera rigs, where three of six pairs never overlap, most of it the essential
matrix's), so a backing-off pair is probed first when the caller gives a cheap check
(``may_fit``: :func:`.verify.may_be_trusted`, H and F from pixels, ~3 ms): no support there, no
fit, and it backs off again (counted as ``probed``). A pair that comes to overlap is found again
within MAX_SKIPPED + 1 windows.

The memory is per stream (one per matcher node, one per offline replay of a bag:
:class:`gcn_match_ros.stream.StreamState`), used in window order; a problem without
``camera_ids`` (a single file) never touches it. Within a window, two threads may look up
different camera pairs at once (:class:`gcn_match_ros.edges.candidates.CandidateJob`): each
pair's entries are its own, and the counts are kept under a lock.
"""
from __future__ import annotations

import threading
from typing import Callable, Dict, Optional, Tuple

import numpy as np

from .verify import MIN_INLIER_RATIO, MIN_INLIERS, PairModel

__all__ = ["RigMemory", "REUSE_SHARE", "MAX_SKIPPED"]

#: A remembered model is reused while its inlier share on the new seeds is at least this
#: fraction of its share at fitting time (and it is still trusted).
REUSE_SHARE = 0.8
#: The most windows a camera pair without a trusted model goes unfitted (module docstring).
MAX_SKIPPED = 7

CameraPair = Tuple[str, str]


class RigMemory:
    """Trusted two-view models by camera pair, and how often they were reused.

    Attributes:
        reused, fitted, invalidated, skipped, probed: counts of model look-ups answered from
            memory, by a new fit, of remembered models that failed the re-check (each also a fit),
            of look-ups of a backing-off pair answered with no model and no fit, and of those
            answered by a probe that found no support (no fit either).
    """

    def __init__(self) -> None:
        self._models: Dict[CameraPair, Tuple[PairModel, float]] = {}
        self._failures: Dict[CameraPair, int] = {}  # failed fits in a row
        self._skips_left: Dict[CameraPair, int] = {}
        self.reused = 0
        self.fitted = 0
        self.invalidated = 0
        self.skipped = 0
        self.probed = 0
        self._counting = threading.Lock()

    def __len__(self) -> int:
        return len(self._models)

    def _count(self, name: str) -> None:
        with self._counting:
            setattr(self, name, getattr(self, name) + 1)

    def model(self, cameras: CameraPair, seeds_a: np.ndarray, seeds_b: np.ndarray,
              fit: Callable[[], Optional[PairModel]], min_inliers: int = MIN_INLIERS,
              min_inlier_ratio: float = MIN_INLIER_RATIO,
              may_fit: Optional[Callable[[], bool]] = None) -> Optional[PairModel]:
        """The trusted (selected) model of ``cameras`` for this window, or None.

        Args:
            cameras: (camera of view a, camera of view b), in the window's view order.
            seeds_a, seeds_b: (S, 2) this window's seed pairs, pixels.
            fit: fits a model on those seeds (called only when memory cannot answer).
            min_inliers, min_inlier_ratio: the trust rule (:meth:`PairModel.trusted`).
            may_fit: a cheap check that ``fit`` could give a trusted model, asked before
                re-fitting a pair whose last fit failed (module docstring); None: always fit.
        """
        remembered = self._models.get(cameras)
        if remembered is not None:
            model, share_at_fit = remembered
            rechecked = model.rechecked(seeds_a, seeds_b)
            if (rechecked.trusted(min_inliers, min_inlier_ratio)
                    and rechecked.inlier_share >= REUSE_SHARE * share_at_fit):
                self._count("reused")
                return rechecked
            self._count("invalidated")
            del self._models[cameras]
        elif self._skips_left.get(cameras, 0) > 0:
            self._skips_left[cameras] -= 1
            self._count("skipped")
            return None
        if cameras in self._failures and may_fit is not None and not may_fit():
            self._count("probed")
            self._failed(cameras)
            return None
        self._count("fitted")
        model = fit()
        if model is None or not model.trusted(min_inliers, min_inlier_ratio):
            self._failed(cameras)
            return None
        self._failures.pop(cameras, None)
        model = model.selected()
        self._models[cameras] = (model, model.inlier_share)
        return model

    def _failed(self, cameras: CameraPair) -> None:
        """One more failed fit of ``cameras`` in a row: back off (module docstring)."""
        failures = self._failures.get(cameras, 0) + 1
        self._failures[cameras] = failures
        self._skips_left[cameras] = min(2 ** failures - 1, MAX_SKIPPED)
