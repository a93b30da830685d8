"""Graceful degradation when matching cannot keep up with the cameras: fewer keypoints.

A window that waits while the worker is busy is replaced by a newer one (``superseded``);
dropping windows alone hides the overload. :class:`KeypointBudget` instead lowers the number
of keypoints per view the worker solves (each frame keeps its best-scored ones,
:func:`gcn_match_ros.windowing.kept_rows`, the same rule as ``max_keypoints``): a solve during
which windows were superseded cuts the budget by ``step`` down to ``floor``, once however many
were (a stream's first window fits every camera pair's model, ~0.3 s at 8 x 500, and each window
superseded meanwhile used to cut the budget again, though the windows after it were solved in
time); once ``calm`` windows in a row
have been solved with at most ``slow_share`` of them taking ``spare`` of the input period or more,
it goes back up by the same factor, up to the configured maximum. The cost of a window grows
faster than linearly with its keypoints, so a modest cut restores the camera rate; the node
reports the budget in ``/diagnostics``. Some slow windows are tolerated because a stream has
periodic ones the budget does not set: a camera pair without a trusted model is re-fitted every
eighth window (:mod:`gcn_match_ros.edges.rig_memory`'s back-off, RANSAC to its last iteration).
Requiring every window of a run to be calm, as before, could never be met then: at 4 x 1000 on
this project's 2-core machine a budget cut to 576 keypoints (frames keeping 576 of 1000, windows
28 ms at the median, one in eight ~130 ms) stayed there for good.
"""
from __future__ import annotations

import collections

__all__ = ["KeypointBudget"]


class KeypointBudget:
    """Keypoints per view the worker solves now (module docstring).

    Args:
        full: the configured maximum (``max_keypoints``); floor: the least it goes to (0 or
            >= full: never degrade).
    Attributes:
        current: the budget now; degraded_windows: windows solved below ``full``.
    """

    def __init__(self, full: int, floor: int, step: float = 0.75, calm: int = 20, spare: float = 0.7,
                 slow_share: float = 0.25) -> None:
        self.full, self.floor = int(full), int(floor)
        self.step, self.calm, self.spare = float(step), int(calm), float(spare)
        self.slow_share = float(slow_share)
        self.current = self.full
        self.degraded_windows = 0
        self._recent: "collections.deque[bool]" = collections.deque(maxlen=self.calm)  # slow or not
        self._cut_since_solved = False

    @property
    def enabled(self) -> bool:
        return 0 < self.floor < self.full

    @property
    def degraded(self) -> bool:
        return self.current < self.full

    def reconfigure(self, full: int) -> None:
        """A new maximum (``max_keypoints`` changed at run time): start from it again."""
        self.full = self.current = int(full)
        self._recent.clear()
        self._cut_since_solved = False

    def behind(self) -> None:
        """A window was superseded: solve fewer keypoints (once until the next window is solved)."""
        if self.enabled and not self._cut_since_solved:
            self.current = max(self.floor, int(self.current * self.step))
            self._cut_since_solved = True
        self._recent.clear()

    def solved(self, compute_s: float, period_s: float, degraded: bool) -> None:
        """A window was solved in ``compute_s``; windows arrive every ``period_s`` (0: unknown);
        ``degraded``: it was cut to the budget."""
        self.degraded_windows += bool(degraded)
        self._cut_since_solved = False
        if not self.degraded or period_s <= 0:
            return
        self._recent.append(compute_s >= self.spare * period_s)
        if len(self._recent) == self.calm and sum(self._recent) <= self.slow_share * self.calm:
            self.current = min(self.full, int(self.current / self.step) + 1)
            self._recent.clear()
