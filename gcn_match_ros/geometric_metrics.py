"""Scores of matches against the true cameras of a posed window — every pair, no depth maps.

Ground-truth labels of pose scenes score only the pairs they can confirm (``data.labels``), a
minority of what a method predicts. These checks score *every* predicted pair from the
cameras alone:

- a pair of keypoints is **epipolar-consistent** when each lies within ``epipolar_px`` of the
  other's epipolar line under the true cameras (:func:`pair_epipolar_px`);
- a **track** is consistent when all its members triangulate at once (DLT,
  :func:`gcn_match_ros.geometry.triangulate_views`) to a point in front of every member's
  camera that reprojects within ``reprojection_px`` into every member view; a track that is
  not keeps its largest consistent subset of members (:func:`consistent_tracks`);
- a predicted pair is **consistent** when it is epipolar-consistent and both its keypoints are
  in their track's consistent subset (:func:`score_geometric`). A soft pair outside any track
  is judged as a track of two (:func:`pairs_consistent`).

Consistency is necessary, not sufficient: a wrong match lying along the epipolar line at a
depth that still projects in front of the cameras passes, so geometric precision is an upper
bound of true precision. :func:`chance_pass_rate` measures how often *random* pairs pass, by
view separation — the part of the bound that is luck. :func:`view_overlap` tells from the
cameras' frusta which view pairs can share points at all.

Poses are world→camera, ``x ~ K (R X + t)`` (``shared/spec/problem-format.md``).
"""
from __future__ import annotations

import dataclasses
import itertools
from typing import Dict, Optional, Sequence, Tuple

import numpy as np

from .geometry import epipolar_distances, fundamental_from_poses, project, triangulate_checked, unproject
from .problem import Problem, Result
from .rounding import tracks_to_pairs
from .view_pairs import by_view_pair

__all__ = ["GeometricTolerance", "GeometricScore", "pair_epipolar_px", "consistent_tracks", "pairs_consistent",
           "score_geometric", "chance_pass_rate", "view_overlap"]


@dataclasses.dataclass(frozen=True)
class GeometricTolerance:
    """epipolar_px: a consistent pair's distance to the epipolar lines; reprojection_px: a
    consistent track's reprojection error in every member view; far_px: a pair this far from
    the epipolar line is certainly wrong (reported apart)."""

    epipolar_px: float = 2.0
    reprojection_px: float = 3.0
    far_px: float = 10.0


def _require_poses(problem: Problem) -> None:
    if not problem.has_poses:
        raise ValueError(f"problem '{problem.name}' has no cameras (K, R, t): cannot score geometrically")


def pair_epipolar_px(problem: Problem, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The larger of the two point-to-epipolar-line distances of each pair under the true
    cameras, pixels.

    Shapes: rows, cols (M,) global keypoint indices in different views -> (M,) float64.
    """
    _require_poses(problem)
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    out = np.full(rows.shape[0], np.inf)
    view = problem.view_index
    va, vb = view[rows], view[cols]
    kp = problem.keypoints.astype(np.float64)
    K, R, t = problem.K, problem.R, problem.t
    for (a, b), m in by_view_pair(va, vb).items():
        F = fundamental_from_poses(K[a], R[a], t[a], K[b], R[b], t[b])
        out[m] = epipolar_distances(F, kp[rows[m]], kp[cols[m]])
    return out


def _members_fit(problem: Problem, members: np.ndarray, tol: GeometricTolerance) -> Tuple[np.ndarray, np.ndarray]:
    """Triangulate each row of ``members`` (B, m) (keypoint indices of different views) from all
    its members: (B,) whether it is in front of every camera and reprojects within tolerance,
    and (B,) its largest reprojection error in pixels."""
    view = problem.view_index[members]                                     # (B, m)
    kp = problem.keypoints.astype(np.float64)[members]                     # (B, m, 2)
    _, err, in_front = triangulate_checked(problem.K[view], problem.R[view], problem.t[view], kp)
    return in_front & (err <= tol.reprojection_px), err


def consistent_tracks(problem: Problem, track: np.ndarray, tol: GeometricTolerance = GeometricTolerance()
                      ) -> np.ndarray:
    """Each track cut to its largest consistent subset of members (see the module docstring;
    ties: the smallest largest reprojection error).

    Shapes: track (N,) ids >= 0 (-1: none), at most one keypoint per view and track -> (N,)
    int64: the same ids for members of the consistent subsets, -1 for every other keypoint
    (tracks left with fewer than two members are dissolved).
    """
    _require_poses(problem)
    track = np.asarray(track, np.int64)
    out = np.full(track.shape, -1, np.int64)
    idx = np.flatnonzero(track >= 0)
    order = idx[np.argsort(track[idx], kind="stable")]
    groups = np.split(order, np.flatnonzero(np.diff(track[order])) + 1) if order.size else []
    by_size: Dict[int, list] = {}
    for g in groups:
        if g.size >= 2:
            by_size.setdefault(g.size, []).append(g)
    for m, gs in by_size.items():
        members = np.stack(gs)                                             # (B, m)
        ok, _ = _members_fit(problem, members, tol)
        for g in members[ok]:
            out[g] = track[g[0]]
        pending = members[~ok]
        for s in range(m - 1, 1, -1):
            if not pending.size:
                break
            subsets = np.array(list(itertools.combinations(range(m), s)))    # (C, s)
            cand = pending[:, subsets]                                      # (B, C, s)
            ok, err = _members_fit(problem, cand.reshape(-1, s), tol)
            ok, err = ok.reshape(cand.shape[:2]), np.where(ok, err, np.inf).reshape(cand.shape[:2])
            found = ok.any(axis=1)
            best = err.argmin(axis=1)
            for b in np.flatnonzero(found):
                keep = cand[b, best[b]]
                out[keep] = track[keep[0]]
            pending = pending[~found]
    return out


def pairs_consistent(problem: Problem, rows: np.ndarray, cols: np.ndarray,
                     tol: GeometricTolerance = GeometricTolerance()) -> np.ndarray:
    """Whether each pair is consistent on its own: epipolar-consistent and a consistent track of two.

    Shapes: rows, cols (M,) -> (M,) bool.
    """
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    if not rows.size:
        return np.zeros(0, bool)
    ok = pair_epipolar_px(problem, rows, cols) <= tol.epipolar_px
    fit, _ = _members_fit(problem, np.stack([rows, cols], axis=1), tol)
    return ok & fit


@dataclasses.dataclass
class GeometricScore:
    """The geometric check of one result's tracks (every pair of keypoints sharing a track).

    Shapes:
        rows, cols: (M,) the predicted pairs, rows < cols.
        epipolar_px: (M,) their distance to the epipolar lines; consistent: (M,) bool.
        separation: (M,) view separation of each pair (difference of the views' numbers).
        consistent_track: (N,) the tracks cut to their consistent subsets (:func:`consistent_tracks`).
    """

    rows: np.ndarray
    cols: np.ndarray
    epipolar_px: np.ndarray
    consistent: np.ndarray
    separation: np.ndarray
    consistent_track: np.ndarray
    far_px: float

    @property
    def precision(self) -> float:
        """Consistent share of the predicted pairs (NaN without pairs): an upper bound of precision."""
        return float(self.consistent.mean()) if self.consistent.size else float("nan")

    def summary(self) -> Dict[str, float]:
        """pairs, consistent, precision, far (share > far_px from the epipolar line), tracks3
        (consistent tracks of >= 3 keypoints)."""
        ids, counts = np.unique(self.consistent_track[self.consistent_track >= 0], return_counts=True)
        return {"pairs": int(self.rows.size), "consistent": int(self.consistent.sum()), "precision": self.precision,
                "far": float((self.epipolar_px > self.far_px).mean()) if self.rows.size else float("nan"),
                "tracks3": int((counts >= 3).sum())}

    def by_separation(self) -> Dict[int, Tuple[int, int]]:
        """separation -> (pairs, consistent pairs)."""
        return {int(s): (int((self.separation == s).sum()), int(self.consistent[self.separation == s].sum()))
                for s in np.unique(self.separation)}


def score_geometric(problem: Problem, result: Result, tol: GeometricTolerance = GeometricTolerance(),
                    view_numbers: Optional[Sequence[int]] = None) -> GeometricScore:
    """Check every pair of a result's tracks against the true cameras (module docstring).

    Args:
        view_numbers: (V,) the views' positions in their sequence (e.g. image numbers), for
            the pairs' view separation; default 0..V-1.
    """
    _require_poses(problem)
    result.validate_against(problem)
    numbers = np.arange(problem.n_views) if view_numbers is None else np.asarray(view_numbers, np.int64)
    if numbers.shape != (problem.n_views,):
        raise ValueError(f"view_numbers: expected {problem.n_views} values, got {numbers.shape}")
    rows, cols = tracks_to_pairs(result.track)
    kept = consistent_tracks(problem, result.track, tol)
    epi = pair_epipolar_px(problem, rows, cols)
    consistent = (epi <= tol.epipolar_px) & (kept[rows] >= 0) & (kept[rows] == kept[cols])
    view = problem.view_index
    separation = np.abs(numbers[view[rows]] - numbers[view[cols]])
    return GeometricScore(rows, cols, epi, consistent, separation, kept, tol.far_px)


def chance_pass_rate(problem: Problem, tol: GeometricTolerance = GeometricTolerance(), pairs: int = 2000,
                     seed: int = 0, view_numbers: Optional[Sequence[int]] = None) -> Dict[int, Tuple[int, int]]:
    """How often random pairs pass :func:`pairs_consistent`: ``pairs`` uniformly drawn keypoint
    pairs per view pair, pooled by view separation -> (tried, passed)."""
    _require_poses(problem)
    rng = np.random.default_rng(seed)
    numbers = np.arange(problem.n_views) if view_numbers is None else np.asarray(view_numbers, np.int64)
    out: Dict[int, Tuple[int, int]] = {}
    for a, b in itertools.combinations(range(problem.n_views), 2):
        na, nb = problem.view_sizes[a], problem.view_sizes[b]
        if not (na and nb):
            continue
        rows = problem.view_offsets[a] + rng.integers(0, na, pairs)
        cols = problem.view_offsets[b] + rng.integers(0, nb, pairs)
        passed = int(pairs_consistent(problem, rows, cols, tol).sum())
        sep = int(abs(numbers[b] - numbers[a]))
        tried, hits = out.get(sep, (0, 0))
        out[sep] = (tried + pairs, hits + passed)
    return out


def view_overlap(problem: Problem, depth_range: Tuple[float, float], grid: int = 24) -> np.ndarray:
    """Which share of each view's image another view sees, from the cameras' frusta: a
    ``grid`` x ``grid`` lattice of view a's pixels, back-projected to every depth in
    ``depth_range`` (8 steps, uniform in 1/z), counts when some depth projects into view b's
    image in front of b.

    Shapes: -> (V, V) float64 in [0, 1], 1 on the diagonal (needs ``image_size``).
    """
    _require_poses(problem)
    if problem.image_size is None:
        raise ValueError(f"problem '{problem.name}' has no image_size: cannot tell what a view sees")
    V = problem.n_views
    z = 1.0 / np.linspace(1.0 / depth_range[0], 1.0 / depth_range[1], 8)
    out = np.eye(V)
    for a in range(V):
        w, h = problem.image_size[a]
        xs, ys = np.meshgrid((np.arange(grid) + 0.5) * w / grid, (np.arange(grid) + 0.5) * h / grid)
        rays = unproject(problem.K[a], np.stack([xs.ravel(), ys.ravel()], axis=1))   # (G, 3), z = 1
        cam = rays[:, None, :] * z[None, :, None]                                   # (G, D, 3)
        world = (cam - problem.t[a]) @ problem.R[a]                                 # R^T (x - t)
        for b in range(V):
            if b == a:
                continue
            uv, depth = project(problem.K[b], problem.R[b], problem.t[b], world)
            wb, hb = problem.image_size[b]
            seen = ((depth > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < wb) & (uv[..., 1] >= 0) & (uv[..., 1] < hb))
            out[a, b] = float(seen.any(axis=1).mean())
    return out
