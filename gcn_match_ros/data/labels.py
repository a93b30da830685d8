"""Ground truth of real scenes: which keypoints of a window image the same scene point.

Ground truth ``gt_track`` (``shared/spec/problem-format.md``: id ≥ 0, ``-1`` unmatched,
``-2`` unlabelled):

Homography scenes (:func:`label_homography`; identical to the reference problems in
``shared/reference/oxford-dev``). For every pair of views a, b each keypoint is
projected into the other image by the exact homography and distances are measured in
that image's pixels.

1. Link (a, i)–(b, j) when, measured in b's pixels, ``H_ab x_i`` and ``x_j`` are mutual
   nearest neighbours less than 3 px apart, or the same holds in a's pixels for
   ``H_ba x_j`` and ``x_i``. Projections outside the other image neither link nor count
   for rule 3.
2. Tracks are the connected components of the links; a component holding two keypoints
   of one view is ``-2`` throughout.
3. An unlinked keypoint whose nearest projected counterpart in some other view is less
   than 10 px away is ``-2`` (localisation noise or a counterpart taken by a closer
   keypoint: neither a sure match nor a sure non-match); other unlinked keypoints are
   ``-1``.

Pose scenes (:func:`label_poses`): there are no depth maps, so a pair can only be
*confirmed* by geometry, never a keypoint proven to have no counterpart unless nothing
lies near its epipolar lines. Rules, for a window of at least 3 views (tolerance
τ = 0.5 px, see below):

1. A pair (a, i)–(b, j) is epipolar-consistent when each point lies within τ of the
   epipolar line of the other (necessary, not sufficient).
2. It is *confirmed* when, in addition, its two-view triangulation lies in front of
   both cameras and, in some third view k, in front of camera k and within τ of a
   keypoint (k, c) that is epipolar-consistent with both (a, i) and (b, j).
3. Uniqueness: when a keypoint has two or more confirmed partners in one view, all those
   links are dropped and every keypoint on them is ``-2`` (which one is right is unknown).
4. Tracks are the connected components of the remaining links; a component holding two
   keypoints of one view, or two members that are not epipolar-consistent, is ``-2``
   throughout (a chain of links that the geometry does not close).
5. A keypoint in no track is ``-1`` when no keypoint of any other view lies within
   10 px of its epipolar lines, else ``-2``. With hundreds of keypoints per view almost
   every unmatched keypoint has such a candidate, so ``-1`` is rare: on these scenes the
   scoring measures pairs among confirmed tracks (a pair joining two different confirmed
   tracks is false), not matches onto unconfirmed keypoints.

Why τ = 0.5 px and not the ~2 px of the data README: the Strecha poses are accurate
(SIFT matches lie a median 0.07 px from their epipolar lines; 85% of descriptor-closed
3-view SIFT triangles on fountain-P11 reproject within 0.5 px), while chance
confirmations grow with the tolerance. Measured with 1000 SIFT keypoints per view on
the three Strecha scenes, by replacing all views but the first two with keypoints of an
unrelated image (every confirmation is then chance): at 2 px, 3-view windows still get
16–35 confirmed pairs between the first two views (13–31% of the real count) and in
6-view windows chance partners make almost every keypoint ambiguous (3–6% stay
labelled); at 0.5 px, 1–4 chance pairs (1–2%) in 3-view and 12–16 (7–11%) in 6-view
windows, while labelling the most true pairs in 6-view windows and within 20% of the
most in 3-view windows (where 0.75–1 px label a few more). A true match outside
τ is not mislabelled: it becomes ``-2``. Large-scale keypoints, which localise worse,
are therefore under-represented among the labelled ones. ORB keypoints sit on the pixel
grid of their pyramid level and repeat less: with the benchmark's 500 keypoints per view
their windows hold 5–20× fewer labelled true pairs than SIFT's (10–230 against 125–1180
on the Strecha windows), of which the same test estimates 3.4% chance (pooled over 15
windows; 8% with 1000 keypoints; up to 25% in a single window of 4 labelled pairs):
``benchmarks/label_chance.py``, ``benchmarks/results/label_chance.md``. ORB scores on
pose scenes are therefore noisy (few pairs a window), not dominated by chance labels.

Photometric labels for pose scenes (:func:`label_photometric`; measured against these in
``benchmarks/results/photometric_labels_check.md``; :func:`.convert.make_problem` and :func:`.convert.convert`
use them with ``pose_labels="photometric"``):
each keypoint's depth by plane sweep against its neighbours in the window
(:mod:`.plane_sweep`: NCC of a fronto-parallel patch, one clear peak), searched over the
depths of the window's :func:`label_poses` tracks (all ``-2`` with fewer than 5). Then as
on homography scenes: projections into view b link mutual nearest keypoints closer than
3 px where the patch also correlates with b at that depth (NCC ≥ 0.7: b sees it); a
keypoint not lifted, not seen by some view, or 3–10 px from a projection is ``-2``; else
``-1``.
"""
from __future__ import annotations

import itertools
from typing import Callable, List, Optional, Sequence, Tuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..geometry import (epipolar_distance_matrix, epipolar_distances, fundamental_from_poses, transfer,
                        triangulate_pair, unproject)
from .plane_sweep import SweepConfig, lift, patch_ncc, project_in_front

__all__ = ["label_homography", "label_poses", "label_photometric", "window_depth_range", "LINK_PX", "IGNORE_PX",
           "EPIPOLAR_PX", "REPROJECT_PX", "PHOTO_SEEN_NCC"]

LINK_PX = 3.0  # homography scenes: a true pair is this close in the target image
IGNORE_PX = 10.0  # both kinds: closer than this but not linked -> unlabelled
EPIPOLAR_PX = 0.5  # pose scenes: epipolar tolerance of a pair (module docstring: why 0.5)
REPROJECT_PX = 0.5  # pose scenes: a confirming keypoint is this close to the reprojection
PHOTO_SEEN_NCC = 0.7  # photometric labels: a lifted patch correlates this well with a view seeing it


def _unit(F: np.ndarray) -> np.ndarray:
    """F scaled to unit Frobenius norm (distances do not depend on it; its magnitude stays sane)."""
    return F / np.linalg.norm(F)


def _inside(xy: np.ndarray, size: np.ndarray) -> np.ndarray:
    """(n,) bool: points (n, 2) inside an image of (width, height)."""
    return (xy[:, 0] >= 0) & (xy[:, 0] < size[0]) & (xy[:, 1] >= 0) & (xy[:, 1] < size[1])


def _nearest(query: np.ndarray, valid: np.ndarray, targets: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """For each query point (n, 2): distance to and index of the nearest target (m, 2);
    ``inf`` and ``-1`` where ``valid`` is False or there are no targets."""
    dist = np.full(len(query), np.inf)
    idx = np.full(len(query), -1, dtype=np.int64)
    if len(targets) and valid.any():
        d, j = cKDTree(targets).query(query[valid])
        dist[valid], idx[valid] = d, j
    return dist, idx


def _tracks(n: int, view: np.ndarray, rows: np.ndarray, cols: np.ndarray,
            consistent: Optional[Callable[[np.ndarray], bool]] = None) -> np.ndarray:
    """Connected components of the links (rows[k], cols[k]) over n keypoints.

    Returns (n,) int64: component id (>= 0) for keypoints with a link, -1 otherwise; -2 for
    components holding two keypoints of one view or failing ``consistent(members)``.
    """
    adj = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    n_comp, comp = connected_components(adj, directed=False)
    sizes = np.bincount(comp, minlength=n_comp)
    track = np.where(sizes[comp] > 1, comp, -1).astype(np.int64)
    linked = np.flatnonzero(track >= 0)
    if not len(linked):
        return track
    # a component's distinct (component, view) keys are fewer than its members -> conflict
    keys = comp[linked] * (int(view.max()) + 1) + view[linked]
    _, first, counts = np.unique(keys, return_index=True, return_counts=True)
    bad = np.unique(comp[linked[first[counts > 1]]])
    if consistent is not None:
        order = linked[np.argsort(comp[linked], kind="stable")]
        groups = np.split(order, np.flatnonzero(np.diff(comp[order])) + 1)
        # two members are one link, which passed the test already
        bad = np.union1d(bad, [comp[g[0]] for g in groups if len(g) > 2 and not consistent(g)])
    track[np.isin(comp, bad) & (track >= 0)] = -2
    return track


def _mutual_links(q_a: np.ndarray, valid: np.ndarray, pts_b: np.ndarray,
                  link_px: float) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Links from view a's keypoints, projected into view b at ``q_a`` (n_a, 2) where
    ``valid``, to b's keypoints ``pts_b`` (n_b, 2): mutual nearest neighbours closer than
    ``link_px`` in b's pixels.

    Returns:
        (ia, jb, d_ab): linked indices into a and b, and (n_a,) distance of every
        projection to its nearest keypoint of b (``inf`` where not valid).
    """
    d_ab, j_ab = _nearest(q_a, valid, pts_b)
    _, i_ba = _nearest(pts_b, np.ones(len(pts_b), bool), q_a[valid])  # back, same pixels
    back = np.full(len(pts_b), -1)
    back[i_ba >= 0] = np.flatnonzero(valid)[i_ba[i_ba >= 0]]
    mutual = (d_ab < link_px) & (j_ab >= 0)
    mutual[mutual] &= back[j_ab[mutual]] == np.flatnonzero(mutual)
    ia = np.flatnonzero(mutual)
    return ia, j_ab[ia], d_ab


def label_homography(keypoints: Sequence[np.ndarray], homographies: np.ndarray, image_sizes: np.ndarray,
                     link_px: float = LINK_PX, ignore_px: float = IGNORE_PX) -> np.ndarray:
    """Ground-truth tracks of keypoints on a plane with exact homographies (rules in the
    module docstring; reproduces the reference problems' ``gt_track``).

    Args:
        keypoints: V arrays (n_v, 2) of pixel (x, y).
        homographies: (V, 3, 3) view v pixels -> a common frame (e.g. the scene's view 0).
        image_sizes: (V, 2) (width, height).

    Returns:
        (N,) int64 gt_track, N = sum n_v, views one after another.
    """
    pts = [np.asarray(k, dtype=np.float64).reshape(-1, 2) for k in keypoints]
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in pts])])
    n = int(offsets[-1])
    view = np.repeat(np.arange(len(pts)), np.diff(offsets))
    near = np.zeros(n, dtype=bool)
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for a, b in itertools.permutations(range(len(pts)), 2):
        # a -> b and b -> a are different tests: each measures in its target's pixels
        H_ab = np.linalg.solve(homographies[b], homographies[a])
        q_a = transfer(H_ab, pts[a])
        ia, jb, d_ab = _mutual_links(q_a, _inside(q_a, image_sizes[b]), pts[b], link_px)
        rows.append(offsets[a] + ia)
        cols.append(offsets[b] + jb)
        near[offsets[a]:offsets[a + 1]] |= d_ab < ignore_px
    track = _tracks(n, view, np.concatenate(rows), np.concatenate(cols))
    track[(track == -1) & near] = -2
    return track



def label_poses(keypoints: Sequence[np.ndarray], K: np.ndarray, R: np.ndarray, t: np.ndarray,
                epipolar_px: float = EPIPOLAR_PX, reproject_px: float = REPROJECT_PX,
                ignore_px: float = IGNORE_PX) -> np.ndarray:
    """Geometric ground-truth tracks from calibrated poses (rules in the module docstring).

    Args:
        keypoints: V >= 3 arrays (n_v, 2) of pixel (x, y).
        K, R: (V, 3, 3); t: (V, 3) world->camera, ``x ~ K (R X + t)``.
        epipolar_px: epipolar tolerance (pairs, and members of one track), pixels.
        reproject_px: how close a confirming keypoint lies to the reprojection, pixels.
        ignore_px: an unlinked keypoint with a keypoint this close to its epipolar line in
            another view is -2 instead of -1.

    Returns:
        (N,) int64 gt_track, N = sum n_v, views one after another.
    """
    n_views = len(keypoints)
    if n_views < 3:
        raise ValueError(f"label_poses needs at least 3 views to confirm a pair, got {n_views}")
    pts = [np.asarray(k, dtype=np.float64).reshape(-1, 2) for k in keypoints]
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in pts])])
    n = int(offsets[-1])
    view = np.repeat(np.arange(n_views), np.diff(offsets))
    F = {(a, b): _unit(fundamental_from_poses(K[a], R[a], t[a], K[b], R[b], t[b]))
         for a, b in itertools.permutations(range(n_views), 2)}
    calib = [unproject(Kv, p)[:, :2] for p, Kv in zip(pts, K)]
    P = [np.c_[Rv, tv] for Rv, tv in zip(R, t)]
    trees = [cKDTree(p) for p in pts]
    near = np.zeros(n, dtype=bool)
    ambiguous = np.zeros(n, dtype=bool)
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for a, b in itertools.combinations(range(n_views), 2):
        if not (len(pts[a]) and len(pts[b])):
            continue
        D = epipolar_distance_matrix(F[a, b], pts[a], pts[b])
        near[offsets[a]:offsets[a + 1]] |= (D < ignore_px).any(axis=1)
        near[offsets[b]:offsets[b + 1]] |= (D < ignore_px).any(axis=0)
        i, j = np.nonzero(D <= epipolar_px)
        X = triangulate_pair(P[a], P[b], calib[a][i], calib[b][j])
        ok = np.all(np.isfinite(X), axis=1)
        ok &= (X @ R[a][2] + t[a][2] > 0) & (X @ R[b][2] + t[b][2] > 0)
        confirmed = np.zeros(len(i), dtype=bool)
        for k in range(n_views):
            if k in (a, b) or not len(pts[k]):
                continue
            cam = X @ R[k].T + t[k]
            test = np.flatnonzero(ok & ~confirmed & (cam[:, 2] > 0))
            proj = cam[test] @ K[k].T
            proj = proj[:, :2] / proj[:, 2:]
            # a few keypoints may lie within the tolerance; any of them may confirm
            n_nb = min(4, len(pts[k]))
            _, c = trees[k].query(proj, k=n_nb, distance_upper_bound=reproject_px)
            c = c.reshape(len(test), n_nb)
            for col in range(n_nb):
                has = c[:, col] < len(pts[k])
                m, cc = test[has], c[has, col]
                good = ((epipolar_distances(F[a, k], pts[a][i[m]], pts[k][cc]) <= epipolar_px)
                        & (epipolar_distances(F[b, k], pts[b][j[m]], pts[k][cc]) <= epipolar_px))
                confirmed[m[good]] = True
        i, j = i[confirmed], j[confirmed]
        # uniqueness: a keypoint with two confirmed partners in this view pair is unresolved
        multi = (np.bincount(i, minlength=len(pts[a]))[i] > 1) | (np.bincount(j, minlength=len(pts[b]))[j] > 1)
        ambiguous[offsets[a] + i[multi]] = True
        ambiguous[offsets[b] + j[multi]] = True
        rows.append(offsets[a] + i[~multi])
        cols.append(offsets[b] + j[~multi])

    kp = np.concatenate(pts)

    def closes(members: np.ndarray) -> bool:
        """Every two members of a chained component are epipolar-consistent."""
        return all(epipolar_distances(F[view[x], view[y]], kp[x][None], kp[y][None])[0] <= epipolar_px
                   for x, y in itertools.combinations(members, 2) if view[x] != view[y])

    track = _tracks(n, view, np.concatenate(rows), np.concatenate(cols), consistent=closes)
    track[ambiguous] = -2
    track[(track == -1) & near] = -2
    return track


def window_depth_range(pts: Sequence[np.ndarray], K: np.ndarray, R: np.ndarray, t: np.ndarray,
                        track: Optional[np.ndarray] = None) -> Optional[Tuple[float, float]]:
    """Depth range to sweep for a pose window: its :func:`label_poses` tracks (``track``, made
    here if not given) triangulated (first two members), depths in every camera, [half the
    2nd, twice the 98th percentile]; None with fewer than 5 tracks."""
    track = label_poses(pts, K, R, t) if track is None else track
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in pts])])
    view = np.repeat(np.arange(len(pts)), np.diff(offsets))
    kp = np.concatenate(pts)
    ids, counts = np.unique(track[track >= 0], return_counts=True)
    ids = ids[counts >= 2]  # uniqueness drops can leave a lone member
    if len(ids) < 5:
        return None
    first = np.array([np.flatnonzero(track == i)[:2] for i in ids])  # members in view order
    calib = [unproject(K[view[m[0]]], kp[m])[:, :2] for m in first.T]
    X = np.array([triangulate_pair(np.c_[R[view[a]], t[view[a]]], np.c_[R[view[b]], t[view[b]]],
                               calib[0][k:k + 1], calib[1][k:k + 1])[0] for k, (a, b) in enumerate(first)])
    z = (np.einsum("vij,nj->vni", R, X) + t[:, None])[..., 2].ravel()
    z = z[np.isfinite(z) & (z > 0)]
    if len(z) < 5:
        return None
    return 0.5 * float(np.percentile(z, 2)), 2.0 * float(np.percentile(z, 98))


def _sweep_support(a: int, n_views: int) -> List[int]:
    """The views a keypoint of window view a is swept against: its neighbours in window order,
    the two nearest on one side at the ends."""
    if a == 0:
        return [1, 2][:n_views - 1]
    if a == n_views - 1:
        return [a - 1, a - 2][:n_views - 1]
    return [a - 1, a + 1]


def label_photometric(keypoints: Sequence[np.ndarray], images: Sequence[np.ndarray], K: np.ndarray,
                      R: np.ndarray, t: np.ndarray, image_sizes: np.ndarray, link_px: float = LINK_PX,
                      ignore_px: float = IGNORE_PX, seen_ncc: float = PHOTO_SEEN_NCC,
                      sweep: SweepConfig = SweepConfig(),
                      z_range: Optional[Tuple[float, float]] = None) -> np.ndarray:
    """Ground-truth tracks on a pose window from photo-consistency (module docstring).

    Args:
        keypoints: V >= 3 arrays (n_v, 2) of pixel (x, y).
        images: V (H, W) float32 grey images of the window's views.
        K, R: (V, 3, 3); t: (V, 3) world->camera, ``x ~ K (R X + t)``.
        image_sizes: (V, 2) (width, height).
        seen_ncc: a lifted keypoint is seen by view b when its patch, at its depth, correlates
            at least this well with what b shows there.
        z_range: depths to sweep; default from the window's :func:`label_poses` tracks.

    Returns:
        (N,) int64 gt_track, N = sum n_v, views one after another; all -2 when the window
        has too few pose-confirmed tracks to bound the scene's depth.
    """
    pts = [np.asarray(k, dtype=np.float64).reshape(-1, 2) for k in keypoints]
    n_views = len(pts)
    if n_views < 3:
        raise ValueError(f"label_photometric needs at least 3 views, got {n_views}")
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in pts])])
    n = int(offsets[-1])
    view = np.repeat(np.arange(n_views), np.diff(offsets))
    z_range = z_range or window_depth_range(pts, K, R, t)
    if z_range is None:
        return np.full(n, -2, dtype=np.int64)
    lifted = [lift(images, K, R, t, a, pts[a], _sweep_support(a, n_views), z_range, sweep) for a in range(n_views)]
    near = np.zeros(n, dtype=bool)
    unknown = np.zeros(n, dtype=bool)  # whether a counterpart exists somewhere is not known
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for a, b in itertools.permutations(range(n_views), 2):
        X, z = lifted[a]
        q_a = project_in_front(K[b], R[b], t[b], X)
        valid = np.all(np.isfinite(q_a), axis=1) & _inside(q_a, image_sizes[b])
        seen = np.zeros(len(q_a), dtype=bool)
        if valid.any():
            ncc = patch_ncc(images, K, R, t, a, pts[a][valid], z[valid][:, None], b, sweep)[:, 0]
            seen[valid] = ncc >= seen_ncc  # NaN (flat, leaves the image) is not seen
        unknown[offsets[a]:offsets[a + 1]] |= ~np.isfinite(z) | (valid & ~seen)
        ia, jb, d_ab = _mutual_links(q_a, seen, pts[b], link_px)
        rows.append(offsets[a] + ia)
        cols.append(offsets[b] + jb)
        near[offsets[a]:offsets[a + 1]] |= d_ab < ignore_px
    track = _tracks(n, view, np.concatenate(rows), np.concatenate(cols))
    track[(track == -1) & (near | unknown)] = -2
    return track

