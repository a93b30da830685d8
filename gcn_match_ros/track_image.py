"""A window's views side by side with its tracks drawn on them (OpenCV; core, no ROS).

:func:`draw_tracks` is what the visualiser node publishes and what a user opens in an image
viewer: each view scaled to one height and dimmed, every keypoint a grey dot, and each track a
polyline through its members (consecutive views) with dots, in one colour per track.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence, Tuple

import cv2
import numpy as np

__all__ = ["draw_tracks", "track_color"]

GAP_PX = 6        # between views
TITLE_PX = 24     # title band above the views
BLANK_GREY = 40   # a view without an image is drawn on this


def track_color(track_id: int) -> Tuple[int, int, int]:
    """A stable, well-spread BGR colour of a track id (golden-ratio hue steps)."""
    hue = int((track_id * 0.618033988749895 % 1.0) * 179)
    bgr = cv2.cvtColor(np.uint8([[[hue, 220, 255]]]), cv2.COLOR_HSV2BGR)[0, 0]
    return int(bgr[0]), int(bgr[1]), int(bgr[2])


def draw_tracks(images: Sequence[Optional[np.ndarray]], keypoints: Sequence[np.ndarray], track: np.ndarray,
                image_sizes: Optional[Sequence[Tuple[int, int]]] = None, height: int = 360, title: str = "",
                link_color: Optional[Callable[[int, int, int], Tuple[int, int, int]]] = None) -> np.ndarray:
    """The views side by side, tracks drawn.

    Args:
        images: per view an image (H, W) grey or (H, W, 3) BGR uint8, or None (a blank view of
            ``image_sizes[v]``, else 640 x 480).
        keypoints: per view (n_v, 2) pixel coordinates, views in window order.
        track: (sum n_v,) track id per keypoint (-1: in no track), rows view after view.
        image_sizes: per view (width, height), used for views without an image.
        height: of every drawn view, pixels.
        title: drawn above the views.
        link_color: colour of the line between members a, b of track t (global rows),
            ``link_color(t, a, b)``; default :func:`track_color` of t.

    Returns:
        (TITLE_PX + height, W, 3) uint8 BGR.
    """
    if len(images) != len(keypoints):
        raise ValueError(f"{len(images)} images for {len(keypoints)} views")
    sizes = [np.asarray(k).shape[0] for k in keypoints]
    track = np.asarray(track, np.int64)
    if track.shape != (sum(sizes),):
        raise ValueError(f"track has {track.shape[0]} entries for {sum(sizes)} keypoints")
    tiles, scales, x0 = [], [], [0]
    for v, img in enumerate(images):
        if img is None:
            w, h = image_sizes[v] if image_sizes is not None and image_sizes[v] else (640, 480)
            img = np.full((max(int(h), 1), max(int(w), 1)), BLANK_GREY, np.uint8)
        else:
            img = (np.asarray(img) * 0.6).astype(np.uint8)  # dimmed: the tracks stand out
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        s = height / img.shape[0]
        tiles.append(cv2.resize(img, (max(int(round(img.shape[1] * s)), 1), height)))
        scales.append(s)
        x0.append(x0[-1] + tiles[-1].shape[1] + GAP_PX)
    canvas = np.full((TITLE_PX + height, max(x0[-1] - GAP_PX, 1), 3), 255, np.uint8)
    for v, tile in enumerate(tiles):
        canvas[TITLE_PX:, x0[v]:x0[v] + tile.shape[1]] = tile
    pts = (np.concatenate([np.asarray(k, np.float64).reshape(-1, 2) * scales[v] + [x0[v], TITLE_PX]
                           for v, k in enumerate(keypoints)]) if sum(sizes) else np.zeros((0, 2)))
    ipts = np.round(pts).astype(np.int64)
    for p in ipts:
        cv2.circle(canvas, (int(p[0]), int(p[1])), 1, (170, 170, 170), -1, cv2.LINE_AA)
    for t in np.unique(track[track >= 0]):
        members = np.flatnonzero(track == t)  # view order: rows are view-major
        for a, b in zip(members[:-1], members[1:]):
            color = link_color(int(t), int(a), int(b)) if link_color else track_color(int(t))
            cv2.line(canvas, tuple(map(int, ipts[a])), tuple(map(int, ipts[b])), color, 1, cv2.LINE_AA)
        for m in members:
            cv2.circle(canvas, tuple(map(int, ipts[m])), 3, track_color(int(t)), -1, cv2.LINE_AA)
    if title:
        cv2.putText(canvas, title, (4, TITLE_PX - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas
