"""Sample bags from the dataset scenes of ``shared/data``, and bags from problems.

Scene -> bag design (:func:`convert_scene_to_bag`; ``gcn-match make-bags`` writes ``bags/``)
------------------------------------------------------------------------------------------
A dataset scene is V images of one static scene taken from V viewpoints (Oxford: a
planar scene, exact homographies; Strecha/Middlebury: calibrated poses). The bag shows
it as a **rig of C cameras sliding along the image sequence**: at time step k,
camera ``cam<j>`` (j = 0..C-1) sees image k + j, for k = 0..V-C. Each time step is one
synchronised rig capture and therefore exactly one matching window of C views (with
the default :class:`~gcn_match_ros.windowing.WindowConfig`), e.g. Oxford graf, C = 3: windows (img1, img2, img3),
(img2, img3, img4), ..., (img4, img5, img6) — the same consecutive windows as
:func:`gcn_match_ros.data.convert.sample_windows`. Every frame is a real image (no image is shown twice by
one camera, nothing is re-published with invented jitter); an image appears in up to
C steps, seen by different cameras, with identical keypoints and labels each time.

Stamps: step k at ``start_time + k / rate_hz``; camera j is stamped ``j * stagger``
later (default 2 ms: a software-triggered rig), well inside the default 50 ms
``sync_tolerance``. Keypoints come from :func:`gcn_match_ros.detect.extract_features` (SIFT by
default, or ORB: packed into ``descriptors_binary``), at most ``max_features`` per
image, strongest first (``scores`` empty). ``camera_info`` holds the scene's K (pose
scenes) or an all-zero K (Oxford: uncalibrated) and the image size; pose scenes also
get ``/<cam>/pose``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Dict, List, Optional, Sequence

import cv2
import numpy as np
from tqdm import tqdm

from ..data import labels as scene_labels
from ..data.scenes import DatasetError, load_scene
from ..detect import DETECTOR_KINDS, extract_features
from ..problem import Problem
from ..stamps import seconds_to_ns
from ..windowing import Frame
from .codec import BINARY_DESCRIPTORS
from .contents import write_scene_bag

__all__ = ["DEFAULT_SCENES", "bag_name", "convert_scene_to_bag", "write_problems_bag"]

#: The scenes of the sample bags in ``bags/`` (``gcn-match make-bags`` without ``--scenes``).
DEFAULT_SCENES = ("oxford/graf", "strecha/fountain-P11")


def bag_name(scene: str, detector: str) -> str:
    """``oxford/graf`` -> ``oxford_graf_<detector>.mcap``; ``strecha/fountain-P11`` ->
    ``strecha_fountain_<detector>.mcap``; ``middlebury_temple`` -> ``middlebury_temple_<detector>.mcap``."""
    parts = [p.split("-")[0] for p in Path(scene).parts]
    return "_".join(parts + [detector]).lower() + ".mcap"


def convert_scene_to_bag(data_root, scene: str, out_path, *, n_cameras: int = 3, detector: str = "sift",
                         max_features: int = 500, rate_hz: float = 2.0, stagger: float = 0.002,
                         start_time: float = 1_700_000_000.0, storage: str = "mcap",
                         progress: bool = True) -> Path:
    """Write a dataset scene as a bag of a C-camera rig sliding along its images (design in
    the module docstring): step k, camera ``cam<j>`` sees image k + j.

    Args:
        data_root: ``shared/data``; scene: e.g. ``oxford/graf``, ``strecha/fountain-P11``.
        n_cameras: C, 2 <= C <= number of images (pose scenes: the labeller needs >= 3 images).
        detector, max_features: :func:`gcn_match_ros.detect.extract_features` settings.
        rate_hz: rig captures per second; stagger: camera j is stamped j * stagger later.
        start_time: stamp of the first capture, seconds (fixed: bags are reproducible).

    Raises:
        DatasetError: missing or malformed scene; ValueError: bad settings.
    """
    sc = load_scene(Path(data_root), scene)
    V = sc.n_views
    if not 2 <= n_cameras <= V:
        raise ValueError(f"n_cameras must be in [2, {V}] for {scene}, got {n_cameras}")
    if rate_hz <= 0 or stagger < 0 or stagger * (n_cameras - 1) >= 1.0 / rate_hz:
        raise ValueError("need rate_hz > 0 and 0 <= stagger * (n_cameras - 1) < 1 / rate_hz")
    feats = []
    for p in tqdm(sc.image_paths, desc=f"{detector} {scene}", unit="image", disable=not progress):
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DatasetError(f"{p}: not a readable image")
        feats.append(extract_features(img, detector, max_features))
    kps = [f.keypoints for f in feats]
    if sc.kind == "homography":
        gt = scene_labels.label_homography(kps, sc.homographies, sc.image_sizes)
        method = f"homography:{sc.name}"
    else:
        gt = scene_labels.label_poses(kps, sc.K, sc.R, sc.t)
        method = f"poses:{sc.name}"
    offsets = np.concatenate([[0], np.cumsum([len(k) for k in kps])])
    per_image = [gt[offsets[v]:offsets[v + 1]] for v in range(V)]
    root = Path(data_root)
    rel = [str(p.relative_to(root)) if p.is_relative_to(root) else p.name for p in sc.image_paths]
    cams = [f"cam{j}" for j in range(n_cameras)]
    start_ns, stagger_ns = seconds_to_ns(start_time), int(round(stagger * 1e9))
    frames: Dict[str, List[Frame]] = {c: [] for c in cams}
    labels: Dict[str, List[np.ndarray]] = {c: [] for c in cams}
    sources: Dict[str, List[str]] = {c: [] for c in cams}
    for k in range(V - n_cameras + 1):
        for j, cam in enumerate(cams):
            v = k + j
            f = feats[v]
            frames[cam].append(Frame(
                camera_id=cam, stamp_ns=start_ns + int(round(k * 1e9 / rate_hz)) + j * stagger_ns,
                keypoints=f.keypoints, descriptors=f.descriptors, frame_id=f"{cam}_optical_frame",
                scales=f.scales, orientations=f.orientations, scores=None,
                K=None if sc.K is None else sc.K[v], image_size=tuple(int(x) for x in sc.image_sizes[v]),
                R=None if sc.R is None else sc.R[v], t=None if sc.t is None else sc.t[v],
                binary=DETECTOR_KINDS[detector][1], descriptor_name=detector))
            labels[cam].append(per_image[v])
            sources[cam].append(rel[v])
    return write_scene_bag(out_path, frames, labels, storage=storage, label_method=method, sources=sources,
                           progress=progress)


def write_problems_bag(path, problems: Sequence[Problem], rate_hz: float = 2.0, stagger: float = 0.002,
                       start_time: float = 1_700_000_000.0, descriptor_name: str = "sift",
                       storage: str = "mcap") -> Path:
    """Write problems as a bag of a rig: problem k is capture step k (stamp
    ``start_time + k / rate_hz``), its view j is camera ``cam<j>`` (stamped ``j * stagger``
    later), with K (``camera_info``), R, t (``/<cam>/pose``) and labels (``gt_track``, made
    scene-global by offsetting each problem's ids past the previous ones') when present.
    ``descriptor_name`` names the problems' descriptors (binary ones: :data:`.codec.BINARY_DESCRIPTORS`).
    Replaying it into the node (or :class:`.source.BagSource`) gives back one window per problem.
    """
    V = max(p.n_views for p in problems)
    cams = [f"cam{j}" for j in range(V)]
    frames: Dict[str, List[Frame]] = {c: [] for c in cams}
    labels: Dict[str, List[Optional[np.ndarray]]] = {c: [] for c in cams}
    base_ns = seconds_to_ns(start_time)
    offset = 0
    for k, p in enumerate(problems):
        gt = None
        if p.gt_track is not None:
            gt = np.where(p.gt_track >= 0, p.gt_track + offset, p.gt_track)
            offset += int(p.gt_track.max(initial=-1)) + 1
        for j in range(p.n_views):
            s = p.view_slice(j)
            opt = (lambda a: None if a is None else a[s])  # noqa: E731
            stamp_ns = base_ns + int(round(k * 1e9 / rate_hz)) + j * int(round(stagger * 1e9))
            frames[cams[j]].append(Frame(
                camera_id=cams[j], stamp_ns=stamp_ns, keypoints=p.keypoints[s], descriptors=p.descriptors[s],
                frame_id=f"{cams[j]}_optical_frame", scales=opt(p.scales), orientations=opt(p.orientations),
                K=None if p.K is None else p.K[j],
                image_size=None if p.image_size is None else tuple(int(x) for x in p.image_size[j]),
                R=None if p.R is None else p.R[j], t=None if p.t is None else p.t[j],
                binary=descriptor_name.lower() in BINARY_DESCRIPTORS, descriptor_name=descriptor_name))
            labels[cams[j]].append(None if gt is None else gt[s])
    return write_scene_bag(path, frames, labels, storage=storage, label_method="problems")
