"""Problem files from the scenes of ``shared/data``: keypoints of a window of views with
their ground truth (:mod:`.labels`); pose scenes also carry K, R, t.

Problem names are ``<scene>_<detector>_<views>``, e.g. ``oxford_graf_sift_123`` or
``strecha_fountain-P11_sift_4-5-6``: the image numbers of the window, joined without a
separator when all are one digit (:func:`problem_name`; read back by
:func:`gcn_match_ros.experiments.images_of`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from tqdm import tqdm

from ..detect import DETECTORS, Features, extract_features
from ..problem import Problem, save_problem
from .labels import label_homography, label_photometric, label_poses
from .scenes import Scene, load_scene, read_gray

__all__ = ["POSE_LABELS", "FeatureCache", "make_problem", "problem_name", "sample_windows", "convert"]

POSE_LABELS = ("geometric", "photometric")

FeatureCache = Dict[Tuple[Path, str, int], Features]


def _features(scene: Scene, v: int, detector: str, max_features: int,
              cache: Optional[FeatureCache]) -> Features:
    key = (scene.image_paths[v], detector, max_features)
    if cache is not None and key in cache:
        return cache[key]
    feats = extract_features(read_gray(scene.image_paths[v]), detector, max_features)
    if cache is not None:
        cache[key] = feats
    return feats


def problem_name(scene: Scene, views: Sequence[int], detector: str) -> str:
    """``<scene>_<detector>_<image numbers>``, numbers joined by '-' unless all are one digit."""
    labels = [scene.view_labels[v] for v in views]
    sep = "" if all(len(x) == 1 for x in labels) else "-"
    return f"{scene.name}_{detector}_{sep.join(labels)}"


def make_problem(scene: Scene, views: Sequence[int], detector: str = "sift", max_features: int = 500,
                 cache: Optional[FeatureCache] = None, pose_labels: str = "geometric") -> Problem:
    """One problem: features of the images ``views`` (indices into the scene) and their
    ground truth; pose scenes also get K, R, t.

    Args:
        cache: optional dict reused across calls so each image is extracted once.
        pose_labels: ground truth of pose scenes: 'geometric' (:func:`label_poses`) or
            'photometric' (:func:`label_photometric`).

    Raises:
        ValueError: fewer than 2 views (3 for pose scenes), a repeated or out-of-range view,
            an unknown ``pose_labels``.
    """
    if pose_labels not in POSE_LABELS:
        raise ValueError(f"pose_labels must be one of {POSE_LABELS}, got {pose_labels!r}")
    views = [int(v) for v in views]
    if len(views) < 2 or len(set(views)) != len(views) or not all(0 <= v < scene.n_views for v in views):
        raise ValueError(f"views must be >= 2 distinct indices in [0, {scene.n_views}), got {views}")
    feats = [_features(scene, v, detector, max_features, cache) for v in views]
    kps = [f.keypoints for f in feats]
    sizes = scene.image_sizes[views]
    poses = {}
    if scene.kind == "homography":
        gt = label_homography(kps, scene.homographies[views], sizes)
    else:
        poses = dict(K=scene.K[views], R=scene.R[views], t=scene.t[views])
        if pose_labels == "photometric":
            images = [read_gray(scene.image_paths[v]).astype(np.float32) for v in views]
            gt = label_photometric(kps, images, image_sizes=sizes, **poses)
        else:
            gt = label_poses(kps, **poses)
    return Problem(view_offsets=np.concatenate([[0], np.cumsum([len(k) for k in kps])]),
                   keypoints=np.concatenate(kps),
                   descriptors=np.concatenate([f.descriptors for f in feats]),
                   scales=np.concatenate([f.scales for f in feats]),
                   orientations=np.concatenate([f.orientations for f in feats]),
                   image_size=sizes, gt_track=gt, name=problem_name(scene, views, detector), **poses)


def sample_windows(scene: Scene, sizes: Sequence[int] = (3, 4, 6), stride: int = 1) -> List[Tuple[int, ...]]:
    """Windows of consecutive views: for each size (in the given order), starts 0, stride,
    2·stride, … while the window fits; sizes larger than the scene give none.

    E.g. 6 Oxford views, sizes (3, 4, 6): (0,1,2), (1,2,3), (2,3,4), (3,4,5), (0,1,2,3), …,
    (0,…,5).
    """
    if stride < 1 or any(s < 2 for s in sizes):
        raise ValueError(f"need stride >= 1 and window sizes >= 2, got stride={stride}, sizes={list(sizes)}")
    return [tuple(range(start, start + s)) for s in sizes
            for start in range(0, scene.n_views - s + 1, stride)]


def convert(data_root: Path, out_dir: Path, scenes: Sequence[str], sizes: Sequence[int] = (3, 4, 6),
            detectors: Sequence[str] = ("sift",), max_features: int = 500, stride: int = 1,
            progress: bool = True, pose_labels: str = "geometric",
            only: Optional[Sequence[str]] = None) -> List[Path]:
    """Write ``<out_dir>/<problem name>.npz`` for every scene × detector × window.

    Args:
        scenes: ids under ``data_root`` (:func:`load_scene`), e.g. ``["oxford/graf",
            "strecha/fountain-P11"]``.
        pose_labels: ground truth of pose scenes (:func:`make_problem`).
        only: problem names to make (:func:`problem_name`); default all.

    Returns:
        The written paths, in scene, detector, window order.

    Raises:
        DatasetError: a scene folder or ground-truth file is missing or malformed.
    """
    for d in detectors:
        if d not in DETECTORS:
            raise ValueError(f"detector must be one of {DETECTORS}, got {d!r}")
    loaded = [load_scene(Path(data_root), s) for s in scenes]  # fail before any work
    jobs = [(sc, det, win) for sc in loaded for det in detectors for win in sample_windows(sc, sizes, stride)
            if only is None or problem_name(sc, win, det) in only]
    cache: FeatureCache = {}
    out: List[Path] = []
    for sc, det, win in tqdm(jobs, desc="problems", unit="problem", disable=not progress):
        problem = make_problem(sc, win, det, max_features, cache, pose_labels)
        path = Path(out_dir) / f"{problem.name}.npz"
        save_problem(problem, path)
        out.append(path)
    return out
