"""A 3-D map of persistent landmarks: what a mapping node builds from the matcher's output.

:class:`LandmarkMap` collects, per landmark id (:mod:`gcn_match_ros.landmarks`), its sightings
— a pixel and the world→camera pose and intrinsics of the view it was seen in — and
triangulates every landmark seen from two or more poses whose rays are not parallel: the
linear point (:func:`gcn_match_ros.geometry.triangulate_views`, an algebraic error that weighs
each sighting by its depth), then ``refine_steps`` Gauss-Newton steps towards the point of least
reprojection error (:func:`gcn_match_ros.geometry.refine_points`). A point is kept only when it
lies in front of every camera and reprojects within ``max_reprojection_px`` into every sighting; otherwise
the landmark stays unmapped (its matches were wrong, or the baseline is too short). Sightings
are bounded per landmark (the latest ``max_sightings``), landmarks unseen for ``max_age_s``
are dropped: the map follows the stream in bounded memory. :meth:`LandmarkMap.held_out_errors`
scores the map on a window before it is added (reprojection error in views it has not used).
"""
from __future__ import annotations

import dataclasses
from typing import Dict, List, Sequence, Tuple

import numpy as np

from .geometry import triangulate_checked, unproject_sightings
from .problem import Problem

__all__ = ["LandmarkMap", "MapConfig", "held_out_sighting_errors", "reprojection_summary"]


@dataclasses.dataclass(frozen=True)
class MapConfig:
    max_reprojection_px: float = 3.0
    min_parallax_deg: float = 1.0
    max_sightings: int = 12
    max_age_s: float = 5.0
    refine_steps: int = 3


@dataclasses.dataclass
class _Sighting:
    xy: np.ndarray    # (2,) pixel
    K: np.ndarray     # (3, 3)
    R: np.ndarray     # (3, 3) world -> camera
    t: np.ndarray     # (3,)


class LandmarkMap:
    """Landmark id -> triangulated world point (module docstring).

    Attributes:
        points: id -> (3,) world point of every mapped landmark.
    """

    def __init__(self, config: MapConfig = MapConfig()) -> None:
        self.config = config
        self._sightings: Dict[int, List[_Sighting]] = {}
        self._seen_ns: Dict[int, int] = {}
        self.points: Dict[int, np.ndarray] = {}

    def add_window(self, landmark_ids: np.ndarray, keypoints: np.ndarray, view_index: np.ndarray,
                   K: np.ndarray, R: np.ndarray, t: np.ndarray, stamp_ns: int) -> List[int]:
        """Add one window's sightings and re-triangulate the landmarks it saw.

        Args:
            landmark_ids: (N,) per keypoint (-1: none); keypoints (N, 2) pixels; view_index (N,).
            K, R, t: (V, 3, 3), (V, 3, 3), (V, 3) intrinsics and world→camera poses of the views.

        Returns:
            the ids whose point was (re)computed and kept.
        """
        cfg = self.config
        seen = np.flatnonzero(np.asarray(landmark_ids) >= 0)
        touched = set()
        for i in seen.tolist():
            lm, v = int(landmark_ids[i]), int(view_index[i])
            s = self._sightings.setdefault(lm, [])
            s.append(_Sighting(np.asarray(keypoints[i], np.float64), K[v], R[v], t[v]))
            del s[:-cfg.max_sightings]
            self._seen_ns[lm] = stamp_ns
            touched.add(lm)
        for lm in [k for k, ns in self._seen_ns.items() if stamp_ns - ns > cfg.max_age_s * 1e9]:
            self._sightings.pop(lm, None)
            self._seen_ns.pop(lm, None)
            self.points.pop(lm, None)
        points = self._triangulate(sorted(touched))
        for lm in touched:
            if lm in points:
                self.points[lm] = points[lm]
            else:
                self.points.pop(lm, None)
        return sorted(points)

    def mapped(self, landmark_ids: np.ndarray) -> List[int]:
        """Indices of the keypoints whose landmark is mapped (:meth:`held_out_errors`' order).

        Shapes: landmark_ids (N,) -> M indices.
        """
        ids = np.asarray(landmark_ids)
        return [i for i in np.flatnonzero(ids >= 0).tolist() if int(ids[i]) in self.points]

    def held_out_errors(self, landmark_ids: np.ndarray, keypoints: np.ndarray, view_index: np.ndarray,
                        K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """How well the map predicts a window it has not seen: the reprojection error of each
        keypoint whose landmark is mapped, its point projected into the keypoint's view. Call it
        before :meth:`add_window` of the same window (then the window is held out); a wrong id
        continuation or a badly triangulated point shows as a large error.

        Args: as :meth:`add_window`.

        Returns:
            (M,) pixels, one per keypoint of a mapped landmark (inf: the point is behind the camera).
        """
        ids = np.asarray(landmark_ids)
        rows = self.mapped(ids)
        if not rows:
            return np.zeros(0)
        X = np.array([self.points[int(ids[i])] for i in rows])                 # (M, 3)
        v = np.asarray(view_index)[rows]
        cam = np.einsum("mij,mj->mi", R[v], X) + t[v]
        px = np.einsum("mij,mj->mi", K[v], cam)
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(px[:, :2] / px[:, 2:] - np.asarray(keypoints, np.float64)[rows], axis=1)
        return np.where((cam[:, 2] > 0) & np.isfinite(err), err, np.inf)

    def _triangulate(self, landmarks: List[int]) -> Dict[int, np.ndarray]:
        """The points of ``landmarks`` that pass the checks (module docstring), by id: landmarks
        with as many sightings are triangulated as one batch (one at a time, a window of ~800
        landmarks took 230 ms)."""
        cfg = self.config
        by_count: Dict[int, List[int]] = {}
        for lm in landmarks:
            if len(self._sightings[lm]) >= 2:
                by_count.setdefault(len(self._sightings[lm]), []).append(lm)
        out = {}
        for group in by_count.values():
            K, R, t, xy = (np.array([[getattr(s, f) for s in self._sightings[lm]] for lm in group])
                           for f in ("K", "R", "t", "xy"))
            centers = -np.einsum("bmji,bmj->bmi", R, t)                         # (B, m, 3)
            rays = np.einsum("bmji,bmj->bmi", R, unproject_sightings(K, xy))
            rays /= np.linalg.norm(rays, axis=2, keepdims=True)
            widest = np.clip(np.einsum("bmi,bni->bmn", rays, rays), -1.0, 1.0).min(axis=(1, 2))
            moved = np.ptp(centers, axis=1).max(axis=1) > 0
            sound = (np.degrees(np.arccos(widest)) >= cfg.min_parallax_deg) & moved
            if not sound.any():
                continue
            X, err, in_front = triangulate_checked(K[sound], R[sound], t[sound], xy[sound], refine=cfg.refine_steps)
            for lm, x, ok in zip(np.asarray(group)[sound].tolist(), X, in_front & (err <= cfg.max_reprojection_px)):
                if ok:
                    out[lm] = x
        return out

    def arrays(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M,) ids, (M, 3) points and (M,) sighting counts of the mapped landmarks, id order."""
        ids = np.array(sorted(self.points), np.int64)
        pts = np.array([self.points[i] for i in ids.tolist()]).reshape(-1, 3)
        counts = np.array([len(self._sightings[i]) for i in ids.tolist()], np.int64)
        return ids, pts, counts


def held_out_sighting_errors(problems: Sequence[Problem], landmark_ids: Sequence[np.ndarray],
                             stamps_ns: Sequence[int], config: MapConfig = MapConfig()) -> Dict[Tuple[int, int], float]:
    """A mapping consumer's view of a sequence's landmark ids: each window is predicted by the
    map of the windows before it (:meth:`LandmarkMap.held_out_errors`), then added.

    Args:
        problems: the windows with K, R, t (world→camera) of every view; landmark_ids: per
            window (N,) ids; stamps_ns: the windows' times.

    Returns:
        (window, keypoint) -> reprojection error [px] of each sighting the map predicted (a
        mapped landmark seen again).
    """
    landmark_map, errors = LandmarkMap(config), {}
    for w, (p, ids, stamp) in enumerate(zip(problems, landmark_ids, stamps_ns)):
        sightings = (ids, p.keypoints, p.view_index, p.K, p.R, p.t)
        keys = [(w, i) for i in landmark_map.mapped(ids)]
        errors.update(zip(keys, landmark_map.held_out_errors(*sightings).tolist()))
        landmark_map.add_window(*sightings, stamp)
    return errors


def reprojection_summary(errors: Sequence[float], config: MapConfig = MapConfig()) -> Dict[str, float]:
    """median_px: median held-out reprojection error; within_px: share within the map's
    ``max_reprojection_px``; predicted: how many (NaN statistics without any); predicted_within:
    how many within it."""
    err = np.asarray(list(errors), np.float64)
    within = err <= config.max_reprojection_px
    return {"median_px": float(np.median(err)) if err.size else float("nan"),
            "within_px": float(np.mean(within)) if err.size else float("nan"),
            "predicted": float(err.size), "predicted_within": float(within.sum())}
