"""Matches and tracks that agree with a window's trusted two-view geometry (pose-free).

A pair of views is, for the purpose of checking matches between them:

- **verified** — it has a trusted model (:meth:`.verify.PairModel.trusted`, from
  :func:`.candidates.candidate_edges`): a pair of its keypoints is kept only if it agrees with
  the model (:meth:`.verify.PairModel.agrees`: an inlier of it);
- **unverifiable** — one of its views has fewer keypoints than a model needs seeds
  (:data:`.verify.MIN_SEEDS`, e.g. a low-texture view): its pairs are kept as scored;
- **unverified** — enough keypoints, yet no trusted model: most often two views that share
  no scene (cameras pointing different ways), where every match is wrong. Only pairs scored
  at least ``unverified_threshold`` are kept.

Tracks must agree *as a whole* (:class:`TrackCheck`): greedy merging joins two tracks through
one good pair, which can chain x_a–y_b and y_b–z_c into a track whose x_a, z_c were never
compared and do not match. Before a merge every two members in a verified view pair must
agree with its model; two members in an unverified view pair must be a kept pair themselves,
or be vouched for by :data:`MIN_WITNESSES` members in views verified against both of theirs
(each keypoint then lies where two epipolar lines cross: a transfer check without a direct
model). This is the cycle consistency the method is about, checked against geometry. Two
members joined only through a third were never matched directly: their pair carries the
localisation error of two links, so it is checked at :data:`CHAIN_SLACK` x the model's
tolerance (at 1x, Oxford graf lost a quarter of its true 4-view tracks).

**Chained models.** A view pair whose descriptor seeds gave no trusted model can still be
linked by tracks through views verified against both: views 0 and 2 of a wide-baseline
sequence, each verified against view 1. Refusing every such chain cost ORB on castle-P19 a
third of its consistent pairs (91 % of those refused were right). So :func:`verified_tracks`
first merges the kept pairs without the track check, takes the pairs these tracks put into
each unverified view pair as seeds, and fits that pair's model on them
(:meth:`WindowGeometry.with_chained_models`); a model with trusted support verifies the view
pair like a direct one. Views that share no scene get no such model: the chains between them
are wrong and random, and no model explains enough of them.
"""
from __future__ import annotations

import math
from typing import Dict, List, Optional, Tuple

import numpy as np

from ..geometry import homogeneous, transfer
from ..problem import Problem
from ..rounding import greedy_tracks, tracks_to_pairs
from .verify import MIN_INLIERS, MIN_SEEDS, PairModel, fit_pair

__all__ = ["WindowGeometry", "TrackCheck", "verified_tracks", "UNVERIFIED_THRESHOLD", "CHAIN_SLACK", "MIN_WITNESSES"]

#: The score a pair of an unverified view pair needs to be kept (see the module docstring).
UNVERIFIED_THRESHOLD = 0.9
#: Tolerance factor for two track members that were not matched directly (module docstring).
CHAIN_SLACK = 2.0
#: Members verified against both views of an unverified pair needed to vouch for it (TrackCheck).
MIN_WITNESSES = 2

ViewPair = Tuple[int, int]


class WindowGeometry:
    """The trusted two-view models of one window and the checks they allow.

    Args:
        problem: the window.
        models: (i, j), i < j -> trusted model or None (:attr:`.candidates.EdgeSet.models`);
            view pairs not listed have none.
        unverified_threshold: the score a pair of an unverified view pair needs.
    """

    def __init__(self, problem: Problem, models: Dict[ViewPair, Optional[PairModel]],
                 unverified_threshold: float = UNVERIFIED_THRESHOLD) -> None:
        self.problem = problem
        self.view_index = problem.view_index
        self.keypoints = problem.keypoints.astype(np.float64)
        self.models = {k: m for k, m in models.items() if m is not None}
        self.small = problem.view_sizes < MIN_SEEDS
        self.unverified_threshold = float(unverified_threshold)
        #: (V, V) symmetric: the view pair has a trusted model
        self.verified = np.zeros((problem.n_views, problem.n_views), bool)
        for a, b in self.models:
            self.verified[a, b] = self.verified[b, a] = True
        #: (V, V) symmetric: no trusted model although both views are large enough for one
        self.unverified = ~self.verified & ~(self.small[:, None] | self.small[None, :])
        self._offsets = problem.view_offsets
        self._view_list = self.view_index.tolist()
        self._small_list = self.small.tolist()
        self._transfers: Dict[ViewPair, tuple] = {}

    def unverified_pairs(self) -> List[ViewPair]:
        """View pairs (a, b), a < b, without a trusted model whose views are large enough to have one."""
        return [(int(a), int(b)) for a, b in np.argwhere(np.triu(self.unverified, 1))]

    def with_chained_models(self, rows: np.ndarray, cols: np.ndarray, scores: np.ndarray,
                            threshold: float) -> "WindowGeometry":
        """This geometry plus the chained model of every unverified view pair that tracks link
        with enough support (module docstring): the tracks are merged greedily from the pairs
        scoring at least ``threshold``, without a track check; their members' pairs in an
        unverified view pair are its seeds. ``self`` when no view pair gains a model.

        Shapes: rows, cols, scores (M,) the pairs :meth:`keep` kept.
        """
        todo = self.unverified_pairs()
        if not todo:
            return self
        chained = greedy_tracks(self.view_index.shape[0], self.view_index, rows, cols, scores, threshold)
        seed_rows, seed_cols = tracks_to_pairs(chained)
        va, vb = self.view_index[seed_rows], self.view_index[seed_cols]
        K = self.problem.K
        models = dict(self.models)
        for a, b in todo:
            m = (va == a) & (vb == b)
            if m.sum() < MIN_INLIERS:
                continue
            model = fit_pair(self.keypoints[seed_rows[m]], self.keypoints[seed_cols[m]],
                             K_a=None if K is None else K[a], K_b=None if K is None else K[b])
            if model is not None and model.trusted():
                models[(a, b)] = model.selected()
        if len(models) == len(self.models):
            return self
        return WindowGeometry(self.problem, models, self.unverified_threshold)

    def _transfer_lists(self, a: int, b: int) -> tuple:
        """For :meth:`agree_pairs`, per keypoint of views a < b what the model maps it to, as
        Python lists: planar — H x_a and H⁻¹ x_b (pixels, :func:`gcn_match_ros.geometry.transfer`);
        else F x_a and Fᵀ x_b (lines); then whether planar and the tolerance. Made on first use."""
        out = self._transfers.get((a, b))
        if out is None:
            model = self.models[(a, b)]
            xa = self.keypoints[self._offsets[a]:self._offsets[a + 1]]
            xb = self.keypoints[self._offsets[b]:self._offsets[b + 1]]
            if model.planar:
                try:
                    fwd, bwd = transfer(model.H, xa), transfer(np.linalg.inv(model.H), xb)
                except np.linalg.LinAlgError:  # no pair agrees with a singular H (as verify.residuals)
                    fwd, bwd = np.full_like(xa, np.nan), np.full_like(xb, np.nan)
                out = (fwd.tolist(), bwd.tolist(), True, model.px)
            else:
                out = ((homogeneous(xa) @ model.F.T).tolist(), (homogeneous(xb) @ model.F).tolist(), False,
                       model.epipolar_px)
            self._transfers[(a, b)] = out
        return out

    def agree_pairs(self, pairs: List[Tuple[int, int]], slack: float = 1.0) -> List[bool]:
        """:meth:`agree` for a few pairs (x, y) at a time, in plain Python: a track check tests
        a handful of pairs per merge, thousands of merges per window, where numpy's per-call
        overhead would dominate. The residuals of :func:`.verify.residuals` (a test holds them
        equal), read from :meth:`_transfer_lists`."""
        view, small, offs, kp = self._view_list, self._small_list, self._offsets, self.keypoints
        out = []
        for x, y in pairs:
            a, b = view[x], view[y]
            if a > b:
                x, y, a, b = y, x, b, a
            if small[a] or small[b]:
                out.append(True)
                continue
            if not self.verified[a, b]:
                out.append(False)
                continue
            fwd, bwd, planar, tol = self._transfer_lists(a, b)
            i, j = x - int(offs[a]), y - int(offs[b])
            xa0, xa1, xb0, xb1 = kp[x, 0], kp[x, 1], kp[y, 0], kp[y, 1]
            if planar:
                tb, ta = fwd[i], bwd[j]
                res = 0.5 * (math.hypot(tb[0] - xb0, tb[1] - xb1) + math.hypot(ta[0] - xa0, ta[1] - xa1))
            else:
                lb, la = fwd[i], bwd[j]
                num = abs(xb0 * lb[0] + xb1 * lb[1] + lb[2])
                den = math.sqrt(lb[0] ** 2 + lb[1] ** 2 + la[0] ** 2 + la[1] ** 2)
                res = num / max(den, 1e-12)
            out.append(res <= slack * tol)
        return out

    def agree(self, rows: np.ndarray, cols: np.ndarray, slack: float = 1.0) -> np.ndarray:
        """Whether each pair may be matched on geometric grounds alone: it agrees with its
        verified view pair's model (:meth:`.verify.PairModel.agrees`, within ``slack`` x its
        tolerance), or its view pair is unverifiable. Pairs of unverified view pairs get False
        (their score decides: :meth:`keep`).

        Shapes: rows, cols (M,) keypoint indices of different views -> (M,) bool.
        """
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        va, vb = self.view_index[rows], self.view_index[cols]
        swap = va > vb
        rows, cols = np.where(swap, cols, rows), np.where(swap, rows, cols)
        va, vb = np.minimum(va, vb), np.maximum(va, vb)
        out = self.small[va] | self.small[vb]
        for (a, b), model in self.models.items():
            m = (va == a) & (vb == b)
            if m.any():
                out[m] = model.agrees(self.keypoints[rows[m]], self.keypoints[cols[m]], slack)
        return out

    def keep(self, rows: np.ndarray, cols: np.ndarray, scores: np.ndarray) -> np.ndarray:
        """(M,) bool: the pairs a solver may publish (module docstring)."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        unverified = self.unverified[self.view_index[rows], self.view_index[cols]]
        return np.where(unverified, np.asarray(scores) >= self.unverified_threshold, self.agree(rows, cols))


class TrackCheck:
    """The ``compatible`` test of :func:`gcn_match_ros.rounding.greedy_tracks` that keeps every
    track consistent as a whole (module docstring).

    Args:
        geometry: the window's models.
        rows, cols: (M,) the kept pairs that may be merged (each already passed
            :meth:`WindowGeometry.keep`): the only pairs of unverified view pairs a track may hold.
    """

    def __init__(self, geometry: WindowGeometry, rows: np.ndarray, cols: np.ndarray) -> None:
        self.geometry = geometry
        n = geometry.view_index.shape[0]
        self._n = n
        self._kept = set((np.minimum(rows, cols).astype(np.int64) * n + np.maximum(rows, cols)).tolist())
        self.refused = 0

    def __call__(self, members_a: List[int], members_b: List[int]) -> bool:
        n = self._n
        unchecked = [(min(x, y), max(x, y)) for x in members_a for y in members_b
                     if min(x, y) * n + max(x, y) not in self._kept]
        if not unchecked:
            return True
        ok = np.array(self.geometry.agree_pairs(unchecked, CHAIN_SLACK))
        if not ok.all():
            rows, cols = np.array(unchecked, np.int64).T
            # unverified view pairs never agree: there two witnesses must vouch
            ok |= self._witnessed(rows, cols, members_a + members_b)
        merged = bool(ok.all())
        self.refused += not merged
        return merged

    def _witnessed(self, rows: np.ndarray, cols: np.ndarray, members: List[int]) -> np.ndarray:
        """(M,) bool: pair m lies in an unverified view pair and at least :data:`MIN_WITNESSES`
        other members sit in views verified against both of its views. Every member's pairs
        in verified view pairs are checked (now or at an earlier merge), so two such witnesses
        pin each keypoint to the intersection of two epipolar lines: a transfer check that
        needs no direct model."""
        view = self.geometry.view_index
        verified = self.geometry.verified
        member_views = view[np.asarray(members, np.int64)]
        out = np.zeros(rows.shape[0], bool)
        for m, (a, b) in enumerate(zip(view[rows].tolist(), view[cols].tolist())):
            if verified[a, b]:
                continue
            others = member_views[(member_views != a) & (member_views != b)]
            witnesses = int((verified[a, others] & verified[b, others]).sum())
            out[m] = witnesses >= MIN_WITNESSES
        return out


def verified_tracks(geometry: WindowGeometry, rows: np.ndarray, cols: np.ndarray, scores: np.ndarray,
                    threshold: float, chained_models: bool = False) -> Tuple[np.ndarray, np.ndarray]:
    """The pairs ``geometry`` keeps, and tracks merged greedily from those scoring at least
    ``threshold`` with every two members agreeing (:class:`TrackCheck`); with
    ``chained_models`` the geometry first gains the chained models of its unverified view
    pairs (module docstring).

    Shapes: rows, cols, scores (M,) -> keep (M,) bool, track (N,) int64 (-1: in no track).
    """
    rows, cols, scores = np.asarray(rows), np.asarray(cols), np.asarray(scores)
    keep = geometry.keep(rows, cols, scores)
    if chained_models:
        chained = geometry.with_chained_models(rows[keep], cols[keep], scores[keep], threshold)
        if chained is not geometry:
            geometry = chained
            keep = geometry.keep(rows, cols, scores)
    merged = keep & (scores >= threshold)
    check = TrackCheck(geometry, rows[merged], cols[merged])
    track = greedy_tracks(geometry.view_index.shape[0], geometry.view_index, rows[keep], cols[keep], scores[keep],
                          threshold, compatible=check)
    return keep, track
