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
tolerance (at 1x, Oxford graf lost a quarter of its true 4-view tracks). A view pair whose model
was fitted coarse (:meth:`.candidates.EdgeConfig.fitted_coarse`: its keypoints showed no
sub-pixel localisation) has its tolerance clipped to the fit's threshold, below three sigma of
noisier keypoints, so its chains are checked at :data:`COARSE_CHAIN_SLACK` (:func:`chain_slack`).
Generated scenes with 1 px of noise fit every view pair coarse: rome16k F1 0.927 -> 0.935 on
windows of their own; the same slack for every view pair cost the 3-D dev windows precision
(0.963 -> 0.955), where most view pairs are fitted fine.

**Rotation cycles.** A trusted model can still be wrong: on a repetitive facade an essential
matrix explains the matches shifted by one window as well as the right ones. With known
intrinsics the window's other views expose it: a model that closes none of the rotation cycles
it is in can be dropped before anything is checked (:mod:`.rotation_cycles`; a solver setting,
off by default: a small object's rotations are too uncertain for the test), and its view pair
is then unverified.

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

import functools
from typing import Callable, Dict, List, Optional, Tuple

import numba
import numpy as np

from ..geometry import homogeneous, transfer, unproject
from ..problem import Problem
from ..rounding import MergeTest, greedy_tracks, relabel_tracks, tracks_to_pairs
from ..view_pairs import by_view_pair, in_view_order
from .candidates import EdgeConfig
from .duplicates import better_placed_members, merge_order
from .neighbourhood import MIN_SHARED, followed_pairs
from .placement import placed_members
from .rotation_cycles import MIN_ROTATION_PAIRS, broken_cycle_pairs, relative_rotation
from .support import unsupported_tracks
from .verify import (MIN_SEEDS, PairModel, f_residual, h_residual, model_matrices, sampson_error_px,
                     transfer_error_px)

__all__ = ["WindowGeometry", "TrackCheck", "checkable_view_pairs", "may_keep", "unverifiable_views", "verified_tracks",
           "chain_slack", "UNVERIFIED_THRESHOLD", "CHAIN_SLACK", "COARSE_CHAIN_SLACK", "MIN_WITNESSES"]

#: The score a pair of an unverified view pair needs to be kept (see the module docstring).
UNVERIFIED_THRESHOLD = 0.9
#: Tolerance factor for two track members that were not matched directly (module docstring).
CHAIN_SLACK = 2.0
#: The same for a view pair whose model was fitted coarse (module docstring, :func:`chain_slack`).
COARSE_CHAIN_SLACK = 3.0
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
        edges: the settings the models were fitted and trusted with; chained models
            (:meth:`with_chained_models`) are fitted and trusted by the same.
    """

    def __init__(self, problem: Problem, models: Dict[ViewPair, Optional[PairModel]],
                 unverified_threshold: float = UNVERIFIED_THRESHOLD, edges: EdgeConfig = EdgeConfig()) -> None:
        self.problem = problem
        self.edges = edges
        self.view_index = problem.view_index
        self.keypoints = problem.keypoints.astype(np.float64)
        self.models = {k: m for k, m in models.items() if m is not None}
        self.small = unverifiable_views(problem)
        self.unverified_threshold = float(unverified_threshold)
        #: (V, V) symmetric: the view pair has a trusted model
        self.verified = np.zeros((problem.n_views, problem.n_views), bool)
        #: (V, V) symmetric: the trusted model is a homography
        self.planar = np.zeros((problem.n_views, problem.n_views), bool)
        for (a, b), model in self.models.items():
            self.verified[a, b] = self.verified[b, a] = True
            self.planar[a, b] = self.planar[b, a] = model.planar
        #: (V, V) symmetric: both views are large enough for a model
        self.checkable = checkable_view_pairs(problem)
        #: (V, V) symmetric: no trusted model although both views are large enough for one
        self.unverified = ~self.verified & self.checkable
        self._offsets = problem.view_offsets

    @property
    def one_plane(self) -> bool:
        """At least three views large enough for a model, every pair of them verified by a
        homography: the window sees one plane, or cameras that only rotate, and every pair is
        checked point to point. Two views are not enough: a homography explains a 3-D scene seen
        with little parallax about as well as F does (generated rigs of two cameras: ids of
        landmarks fragmented 1.11 -> 1.41 per point when such windows counted)."""
        if int((~self.small).sum()) < 3:
            return False
        return bool(self.planar[np.triu(self.checkable, 1)].all())

    def unverified_pairs(self) -> List[ViewPair]:
        """View pairs (a, b), a < b, without a trusted model whose views are large enough to have one."""
        return [(int(a), int(b)) for a, b in np.argwhere(np.triu(self.unverified, 1))]

    def with_chained_models(self, rows: np.ndarray, cols: np.ndarray, scores: np.ndarray,
                            threshold: float) -> "WindowGeometry":
        """This geometry plus the chained model of every unverified view pair that tracks link
        with enough support (module docstring): the tracks are merged greedily from the pairs
        scoring at least ``threshold``, without a track check; their members' pairs in an
        unverified view pair are its seeds, fitted and trusted as the candidates' models are
        (:attr:`edges`). ``self`` when no view pair gains a model.

        Shapes: rows, cols, scores (M,) the pairs :meth:`keep` kept.
        """
        todo = self.unverified_pairs()
        if not todo:
            return self
        chained = greedy_tracks(self.view_index.shape[0], self.view_index, rows, cols, scores, threshold)
        seed_rows, seed_cols = tracks_to_pairs(chained)
        groups = by_view_pair(self.view_index[seed_rows], self.view_index[seed_cols])
        K = self.problem.K
        models = dict(self.models)
        for a, b in todo:
            m = groups.get((a, b))
            if m is None or m.size < self.edges.min_inliers:
                continue
            model = self.edges.trusted(self.edges.fit(self.keypoints[seed_rows[m]], self.keypoints[seed_cols[m]],
                                                      None if K is None else K[a], None if K is None else K[b]))
            if model is not None:
                models[(a, b)] = model
        if len(models) == len(self.models):
            return self
        return WindowGeometry(self.problem, models, self.unverified_threshold, self.edges)

    def with_closed_rotation_cycles(self, rows: np.ndarray, cols: np.ndarray) -> "WindowGeometry":
        """This geometry without the essential-matrix models that close none of the rotation
        cycles they are in (:mod:`.rotation_cycles`); each model's rotation is chosen by the
        pairs among ``rows``, ``cols`` that agree with it, and tested with at least
        :data:`.rotation_cycles.MIN_ROTATION_PAIRS` of them. ``self`` when none is dropped or the
        views are uncalibrated.

        Shapes: rows, cols (M,) keypoint indices of different views.
        """
        K = self.problem.K
        if K is None:
            return self
        rows, cols, va, vb = self.in_view_order(rows, cols)
        agreeing = self.agree(rows, cols)
        groups = by_view_pair(va, vb)
        rotations = {}
        for (a, b), model in self.models.items():
            m = groups.get((a, b))
            if model.planar or not model.essential or m is None:
                continue
            m = m[agreeing[m]]
            if m.size < MIN_ROTATION_PAIRS:
                continue
            R = relative_rotation(K[b].T @ model.F @ K[a], unproject(K[a], self.keypoints[rows[m]])[:, :2],
                                  unproject(K[b], self.keypoints[cols[m]])[:, :2])
            if R is not None:
                rotations[(a, b)] = R
        broken = broken_cycle_pairs(rotations)
        if not broken:
            return self
        return WindowGeometry(self.problem, {k: m for k, m in self.models.items() if k not in broken},
                              self.unverified_threshold, self.edges)

    def transfers(self, a: int, b: int) -> tuple:
        """Per keypoint of views a < b (verified) what their model maps it to: planar — H x_a
        and H⁻¹ x_b (pixels, :func:`gcn_match_ros.geometry.transfer`, in (n, 3) with a zero
        last column); else F x_a and Fᵀ x_b (lines); then whether planar and the tolerance
        (:attr:`.verify.PairModel.inlier_rule`).

        Returns: (n_a, 3), (n_b, 3) float64, bool, float.
        """
        model = self.models[(a, b)]
        xa = self.keypoints[self._offsets[a]:self._offsets[a + 1]]
        xb = self.keypoints[self._offsets[b]:self._offsets[b + 1]]
        planar, tolerance = model.inlier_rule
        if planar:
            if model.H_inverse is None:  # no pair agrees with a singular H (as verify.residuals)
                fwd, bwd = np.full_like(xa, np.nan), np.full_like(xb, np.nan)
            else:
                fwd, bwd = transfer(model.H, xa), transfer(model.H_inverse, xb)
            return np.pad(fwd, ((0, 0), (0, 1))), np.pad(bwd, ((0, 0), (0, 1))), True, tolerance
        return homogeneous(xa) @ model.F.T, homogeneous(xb) @ model.F, False, tolerance

    def in_view_order(self, rows: np.ndarray, cols: np.ndarray) -> Tuple[np.ndarray, ...]:
        """The pairs with each one's keypoint of the lower view first, and their views.

        Shapes: rows, cols (M,) -> rows, cols, view of rows, view of cols (M,) int64.
        """
        return in_view_order(self.view_index, rows, cols)

    def agree(self, rows: np.ndarray, cols: np.ndarray, slack: float = 1.0) -> np.ndarray:
        """Whether each pair may be matched on geometric grounds alone: it agrees with its
        verified view pair's model (:meth:`.verify.PairModel.agrees`, within ``slack`` x its
        tolerance), or its view pair is unverifiable. Pairs of unverified view pairs get False
        (their score decides: :meth:`keep`).

        Shapes: rows, cols (M,) keypoint indices of different views -> (M,) bool.
        """
        rows, cols, va, vb = self.in_view_order(rows, cols)
        out = ~self.checkable[va, vb]
        slot, matrices, by_h, tolerance = self._agreement_tables
        _pairs_agree(self.keypoints, rows, cols, slot[va, vb], *matrices, by_h, tolerance, float(slack), out)
        return out

    @functools.cached_property
    def model_slots(self) -> Tuple[np.ndarray, List[ViewPair]]:
        """The view pairs (a, b), a < b, with a trusted model, sorted, and each one's place in that
        list at [a, b] of a (V, V) int64 table (-1 everywhere else): how the compiled checks find a
        view pair's model in arrays stacked in that order."""
        pairs = sorted(self.models)
        V = self.verified.shape[0]
        slot = np.full((V, V), -1, np.int64)
        for p, (a, b) in enumerate(pairs):
            slot[a, b] = p
        return slot, pairs

    @functools.cached_property
    def _agreement_tables(self):
        """:attr:`model_slots`' table and each model as :func:`_pairs_agree` reads it, in that
        order: :func:`.verify.model_matrices` of the selected model stacked, and
        :attr:`.verify.PairModel.inlier_rule` (whether the H residual is read, the tolerance)."""
        slot, pairs = self.model_slots
        parts = [model_matrices(self.models[ab].selected()) + self.models[ab].inlier_rule for ab in pairs]
        empty = np.zeros((0, 3, 3))
        H, Hi, F = ((np.array([q[k] for q in parts]) if parts else empty) for k in range(3))
        has_h, has_f, by_h = (np.array([q[k] for q in parts], bool) for k in (3, 4, 5))
        return slot, (H, Hi, F, has_h, has_f), by_h, np.array([q[6] for q in parts], np.float64)

    def keep(self, rows: np.ndarray, cols: np.ndarray, scores: np.ndarray) -> np.ndarray:
        """(M,) bool: the pairs a solver may publish (module docstring)."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        return np.where(self._in_unverified(rows, cols), np.asarray(scores) >= self.unverified_threshold,
                        self.agree(rows, cols))

    def _in_unverified(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(M,) bool: the pair's view pair is unverified (:attr:`unverified`)."""
        return self.unverified[self.view_index[rows], self.view_index[cols]]


def unverifiable_views(problem: Problem) -> np.ndarray:
    """(V,) bool: the views with fewer keypoints than a two-view model needs seeds
    (:data:`.verify.MIN_SEEDS`); every view pair with one is unverifiable (module docstring)."""
    return problem.view_sizes < MIN_SEEDS


def checkable_view_pairs(problem: Problem) -> np.ndarray:
    """(V, V) bool, symmetric: both views have keypoints enough for a two-view model (neither is
    :func:`unverifiable_views`), so the view pair's pairs can be checked against one."""
    small = unverifiable_views(problem)
    return ~(small[:, None] | small[None, :])


def chain_slack(model: PairModel, edges: EdgeConfig) -> float:
    """The tolerance factor :class:`TrackCheck` holds two members of a view pair to that were not
    matched directly: :data:`COARSE_CHAIN_SLACK` where ``edges`` fitted ``model`` coarse
    (:meth:`.candidates.EdgeConfig.fitted_coarse`), else :data:`CHAIN_SLACK` (module docstring)."""
    return COARSE_CHAIN_SLACK if edges.fitted_coarse(model) else CHAIN_SLACK


def may_keep(model: Optional[PairModel], checkable: bool, res_h: np.ndarray, res_f: np.ndarray) -> np.ndarray:
    """Which candidate pairs of one view pair :meth:`WindowGeometry.keep` keeps at some score, from
    their residuals under the view pair's trusted ``model`` (:func:`.verify.residuals`, as the
    candidate edges compute them): every pair of a view pair that is unverifiable (not
    ``checkable``: a view with fewer keypoints than a model needs, :func:`checkable_view_pairs`)
    or unverified (no model: its pairs are kept on their score), else those that agree with the
    model (:meth:`.verify.PairModel.agreeing`). A pair outside is dropped whatever its score, so a
    solver need not score it; the candidate edges apply this to each view pair as they find it.

    Shapes: res_h, res_f (M,) -> (M,) bool.
    """
    if model is None or not checkable:
        return np.ones(res_h.shape[0], bool)
    return model.agreeing(res_h, res_f)


class TrackCheck(MergeTest):
    """The ``compatible`` test of :func:`gcn_match_ros.rounding.greedy_tracks` that keeps every
    track consistent as a whole (module docstring), compiled: a window asks it thousands of
    times, a handful of member pairs each.

    Args:
        geometry: the window's models.
        rows, cols: (M,) the kept pairs that may be merged (each already passed
            :meth:`WindowGeometry.keep`): the only pairs of unverified view pairs a track may hold.

    Attributes:
        refused: merges refused so far.
    """

    def __new__(cls, geometry: WindowGeometry, rows: np.ndarray, cols: np.ndarray) -> "TrackCheck":
        n = geometry.view_index.shape[0]
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        # both orders: a merge looks its member pairs up as they come (a binary search, which a
        # sort is enough for: numpy's hashing np.unique took 2.5x as long)
        kept = np.sort(np.concatenate([rows * n + cols, cols * n + rows]))
        pair, pairs = geometry.model_slots
        fwd, bwd, planar, chain_tol = [np.zeros((0, 3))], [np.zeros((0, 3))], [], []
        fwd_start, bwd_start = [], []
        n_fwd = n_bwd = 0
        for a, b in pairs:
            f, g, is_planar, t = geometry.transfers(a, b)
            fwd.append(f); bwd.append(g); planar.append(is_planar)
            chain_tol.append(chain_slack(geometry.models[(a, b)], geometry.edges) * t)
            fwd_start.append(n_fwd); bwd_start.append(n_bwd)
            n_fwd += f.shape[0]; n_bwd += g.shape[0]
        data = (kept, np.int64(n), geometry.view_index.astype(np.int64), geometry.problem.view_offsets.astype(np.int64),
                geometry.keypoints, geometry.small, geometry.verified, pair,
                np.array(fwd_start, np.int64), np.array(bwd_start, np.int64), np.concatenate(fwd),
                np.concatenate(bwd), np.array(planar, bool), np.array(chain_tol, np.float64),
                np.int64(MIN_WITNESSES), np.zeros(1, np.int64))
        return super().__new__(cls, _track_agrees, data)

    @property
    def refused(self) -> int:
        return int(self.data[-1][0])


@numba.njit(cache=True, nogil=True)
def _pairs_agree(kp, rows, cols, slot, H, Hi, F, has_h, has_f, by_h, tolerance, slack, out):
    """out[m] = whether pair (rows[m], cols[m]) agrees with the selected model of its view pair's
    slot[m] (:meth:`.verify.PairModel.agrees`: the same residuals, :func:`.verify.h_residual` and
    :func:`.verify.f_residual`, and rule); pairs without a slot (-1) keep their out. Compiled: a
    window checks ~20 k candidate pairs, and gathering them per view pair in numpy cost ~0.2 ms a
    view pair.

    Shapes: kp (N, 2) float64; rows, cols, slot (M,) int64 (rows in the lower view); H, Hi, F
    (P, 3, 3); has_h, has_f, by_h (P,) bool; tolerance (P,); out (M,) bool, written in place."""
    for m in range(rows.shape[0]):
        p = slot[m]
        if p < 0:
            continue
        a, b = rows[m], cols[m]
        x, y, u, v = kp[a, 0], kp[a, 1], kp[b, 0], kp[b, 1]
        if by_h[p]:
            residual = h_residual(x, y, u, v, H[p], Hi[p]) if has_h[p] else np.inf
        else:
            residual = f_residual(x, y, u, v, F[p]) if has_f[p] else np.inf
        out[m] = residual <= slack * tolerance[p]


@numba.njit(cache=True)
def _track_agrees(data, members, n_a, n_b):
    """:class:`TrackCheck`'s test: every pair of a first-track member x and a second-track
    member y is a kept pair, agrees with its verified view pair's model within the pair's chain
    tolerance (:func:`chain_slack` x its tolerance; the residuals of :func:`.verify.residuals`, by
    the same formulas), lies in an unverifiable view pair, or — in an unverified one — has
    MIN_WITNESSES members in views verified against both."""
    (kept, n, view, offsets, kp, small, verified, pair, fwd_start, bwd_start, fwd, bwd, planar, chain_tol,
     min_witnesses, refused) = data
    for s in range(n_a):
        x = members[s]
        for t in range(n_a, n_a + n_b):
            y = members[t]
            key = x * n + y
            at = np.searchsorted(kept, key)
            if at < kept.shape[0] and kept[at] == key:
                continue
            a, b, xa, yb = view[x], view[y], x, y
            if a > b:
                a, b, xa, yb = b, a, y, x
            if small[a] or small[b]:
                continue
            if verified[a, b]:
                p = pair[a, b]
                i, j = fwd_start[p] + xa - offsets[a], bwd_start[p] + yb - offsets[b]
                if planar[p]:
                    res = transfer_error_px(fwd[i, 0], fwd[i, 1], kp[yb, 0], kp[yb, 1], bwd[j, 0], bwd[j, 1],
                                            kp[xa, 0], kp[xa, 1])
                else:
                    res = sampson_error_px(fwd[i, 0], fwd[i, 1], fwd[i, 2], bwd[j, 0], bwd[j, 1], kp[yb, 0], kp[yb, 1])
                if res <= chain_tol[p]:
                    continue
                refused[0] += 1
                return False
            # an unverified view pair: witnesses must vouch (TrackCheck's docstring)
            witnesses = 0
            for u in range(n_a + n_b):
                w = view[members[u]]
                if w != a and w != b and verified[a, w] and verified[b, w]:
                    witnesses += 1
            if witnesses < min_witnesses:
                refused[0] += 1
                return False
    return True


def verified_tracks(geometry: WindowGeometry, rows: np.ndarray, cols: np.ndarray, scores: np.ndarray,
                    threshold: float, chained_models: bool = False, rotation_cycles: bool = False,
                    neighbours: int = 0, min_shared: int = MIN_SHARED,
                    judge: Optional[Callable[[np.ndarray, np.ndarray], np.ndarray]] = None,
                    prefer_localised: bool = False, planar_threshold: Optional[float] = None,
                    support_threshold: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
    """The pairs ``geometry`` keeps, and tracks merged greedily from those scoring at least
    ``threshold`` with every two members agreeing (:class:`TrackCheck`). In a window that sees
    one plane (:attr:`WindowGeometry.one_plane`) the pairs checked by its homographies merge at
    ``planar_threshold`` when given: the precision-first threshold guards against repetitions
    along epipolar lines, which a point-to-point check does not let through. In every other
    window a pair scored at least ``planar_threshold`` may add to a track a keypoint its members
    place point to point (:mod:`.placement`). With
    ``prefer_localised``, tracks of a one-plane window take of near-duplicate keypoints the ones
    the homographies place best (:mod:`.duplicates`: ranked before the merge, exchanged after it). With
    ``rotation_cycles`` the models that close none of their rotation cycles are dropped first
    (:meth:`WindowGeometry.with_closed_rotation_cycles`); with ``chained_models`` the geometry
    then gains the chained models of its unverified view pairs (module docstring). With
    ``neighbours`` = k > 0, a kept pair that ``judge`` (rows, cols) -> bool picks (None: every
    one) and that shares fewer than ``min_shared`` of its k nearest kept pairs scoring at least
    ``threshold`` in both views is dropped before the tracks are merged (:mod:`.neighbourhood`).
    With ``support_threshold`` > 0, a track of two that other views verified against both should
    show, yet none joined, is dissolved unless its pair scores at least that (:mod:`.support`).

    Shapes: rows, cols, scores (M,) -> keep (M,) bool, track (N,) int64 (-1: in no track).
    """
    rows, cols, scores = np.asarray(rows), np.asarray(cols), np.asarray(scores)
    if rotation_cycles:
        geometry = geometry.with_closed_rotation_cycles(rows, cols)
    keep = geometry.keep(rows, cols, scores)
    direct = geometry  # the models of the view pairs' own seeds: what places a keypoint (.placement)
    if chained_models:
        chained = geometry.with_chained_models(rows[keep], cols[keep], scores[keep], threshold)
        if chained is not geometry:
            geometry = chained
            keep = geometry.keep(rows, cols, scores)
    one_plane = geometry.one_plane
    merge_at = threshold
    if one_plane and planar_threshold is not None:
        # pairs with a view too small for a model are kept as scored, not checked point to point
        unchecked = ~geometry.checkable[geometry.view_index[rows], geometry.view_index[cols]]
        merge_at = np.where(unchecked, threshold, planar_threshold)
    merged = keep & (scores >= merge_at)
    if neighbours:
        judged = keep.copy()
        if judge is not None:
            judged[keep] = judge(rows[keep], cols[keep])
        keep &= followed_pairs(geometry.keypoints, geometry.view_index, rows, cols, judged, merged, neighbours,
                               min_shared)
        merged &= keep
    check = TrackCheck(geometry, rows[merged], cols[merged])
    keys = merge_order(geometry, rows, cols, scores, merged) if prefer_localised and one_plane else scores
    track = greedy_tracks(geometry.view_index.shape[0], geometry.view_index, rows[merged], cols[merged],
                          keys[merged], -np.inf, compatible=check)
    if prefer_localised and one_plane:
        track = better_placed_members(geometry, track)
    if not one_plane and planar_threshold is not None and planar_threshold < threshold:
        direct_check = check if direct is geometry else TrackCheck(direct, rows[merged], cols[merged])
        track = placed_members(direct, track, rows[keep], cols[keep], scores[keep], planar_threshold, threshold,
                               direct_check)
    if support_threshold > 0:
        dissolved = unsupported_tracks(geometry, track, rows[merged], cols[merged], scores[merged], support_threshold)
        if dissolved.size:
            track = relabel_tracks(np.where(np.isin(track, dissolved), -1, track))
    return keep, track
