"""Multi-view matching problems and results: the `.npz` interchange contract.

Implements ``shared/spec/problem-format.md`` exactly. A *problem* holds N keypoints
of V views stored one view after another (``view_offsets``); a *result* holds the
cycle-consistent tracks and the soft pair scores of one matcher.

Files are plain ``numpy.savez`` archives read with ``allow_pickle=False``; every
malformed key raises :class:`FormatError` naming that key.
"""
from __future__ import annotations

import dataclasses
import os
import tempfile
from pathlib import Path
from typing import Dict, Optional, Tuple

import numpy as np

__all__ = ["FormatError", "Problem", "Result", "load_problem", "save_problem",
           "load_result", "save_result", "atomic_write", "keypoint_range_fault", "descriptor_range_fault",
           "intrinsics_fault", "rotation_fault", "MAX_ABS_PIXEL", "MAX_ABS_DESCRIPTOR", "IMAGE_MARGIN_PX",
           "ROTATION_TOLERANCE"]

#: Largest |pixel coordinate| accepted when the image size is unknown (no camera is that big).
MAX_ABS_PIXEL = 1e5
#: Largest |descriptor value| accepted (SIFT bytes <= 255, ORB bits, learned descriptors ~1).
MAX_ABS_DESCRIPTOR = 1e6
#: Keypoints may sit this far outside the image (sub-pixel refinement at the border).
IMAGE_MARGIN_PX = 1.0
#: Largest |R Rᵀ − I| entry of a rotation (the datasets' stored rotations: ~1e-6).
ROTATION_TOLERANCE = 1e-4


class FormatError(ValueError):
    """A problem or result file (or array) breaks the contract; the message names the key."""


def _as(arr, dtype, key: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.dtype.kind in "OUSV":
        raise FormatError(f"'{key}': expected numeric dtype {np.dtype(dtype)}, got {a.dtype}")
    if np.dtype(dtype).kind == "i" and a.dtype.kind == "f":
        if a.size and not np.all(np.isfinite(a) & (a == np.round(a))):
            raise FormatError(f"'{key}': expected integers, got non-integral floats")
    return np.ascontiguousarray(a, dtype=dtype)


def _check_shape(a: np.ndarray, shape: tuple, key: str) -> None:
    """``shape`` entries of None match any size."""
    ok = a.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, a.shape))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise FormatError(f"'{key}': expected shape {want}, got {tuple(a.shape)}")


def _check_finite(a: np.ndarray, key: str) -> None:
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise FormatError(f"'{key}': contains NaN or inf")


# Finite values no camera or detector produces: the similarity of such descriptors overflows to
# NaN, such coordinates or focal lengths make the two-view fits meaningless (a focal length of 0
# makes the essential matrix's threshold infinite). One rule for problems and for frames
# (:func:`gcn_match_ros.windowing.validate_frame`).

def keypoint_range_fault(keypoints: np.ndarray, image_size: Optional[np.ndarray] = None) -> Optional[str]:
    """Why keypoints cannot be pixels of a camera, or None when they can: outside the image (by more
    than :data:`IMAGE_MARGIN_PX`) where its size is known, else a coordinate beyond
    :data:`MAX_ABS_PIXEL`.

    Shapes: keypoints (n, 2); image_size (2,) (width, height; a size that is not positive is
    unknown) or None.
    """
    kp = np.asarray(keypoints)
    if kp.size == 0:
        return None
    size = None if image_size is None else np.asarray(image_size, np.float64)
    if size is None or not np.all(size > 0):  # every window's problem passes here: one pass, no copies but |kp|
        far = float(np.abs(kp).max())
        return None if far <= MAX_ABS_PIXEL else \
            f"keypoint coordinates up to {far:.3g} px (more than {MAX_ABS_PIXEL:.0e}: not from a camera)"
    outside = np.any((kp < -IMAGE_MARGIN_PX) | (kp > size + IMAGE_MARGIN_PX), axis=1)
    if not outside.any():
        return None
    i = int(np.flatnonzero(outside)[0])
    return (f"{int(outside.sum())} keypoints outside their image (e.g. #{i} at {kp[i].tolist()} in a "
            f"{int(size[0])} x {int(size[1])} image)")


def descriptor_range_fault(descriptors: np.ndarray) -> Optional[str]:
    """Why descriptors cannot come from a detector (a value beyond :data:`MAX_ABS_DESCRIPTOR`), or None.

    Shapes: descriptors (n, D).
    """
    d = np.asarray(descriptors)
    largest = float(np.abs(d).max()) if d.size else 0.0
    return f"descriptor values up to {largest:.3g} (more than {MAX_ABS_DESCRIPTOR:.0e})" \
        if largest > MAX_ABS_DESCRIPTOR else None


def intrinsics_fault(K: np.ndarray) -> Optional[str]:
    """Why K is not a pinhole camera matrix, or None when it is: not finite, a focal length fx or fy
    not positive, or a last row other than (0, 0, 1).

    Shapes: K (3, 3), or (V, 3, 3) checked view by view.
    """
    K = np.asarray(K, np.float64)
    if not np.all(np.isfinite(K)):
        return "not finite"
    views = K.reshape(-1, 3, 3)
    no_focal = ~((views[:, 0, 0] > 0) & (views[:, 1, 1] > 0))
    bad_row = np.abs(views[:, 2] - (0.0, 0.0, 1.0)).max(axis=1) > 1e-6
    if not (no_focal.any() or bad_row.any()):
        return None
    v = int(np.flatnonzero(no_focal | bad_row)[0])
    k, at = views[v], (f" (view {v})" if K.ndim == 3 else "")
    if no_focal[v]:
        return f"focal lengths fx = {k[0, 0]:.6g}, fy = {k[1, 1]:.6g}{at}: both must be positive"
    return f"last row {k[2].tolist()}{at}: must be (0, 0, 1)"


def rotation_fault(R: np.ndarray) -> Optional[str]:
    """Why R is not a rotation matrix (R Rᵀ = I within :data:`ROTATION_TOLERANCE`, det R = +1), or None
    when it is: a world→camera pose with another R (a scaled K·R, a reflection) gives training's
    epipolar loss and the geometric scores wrong cameras.

    Shapes: R (3, 3), or (V, 3, 3) checked view by view.
    """
    views = np.asarray(R, np.float64).reshape(-1, 3, 3)
    off = np.abs(np.einsum("vij,vkj->vik", views, views) - np.eye(3)).max(axis=(1, 2))
    bad = (off > ROTATION_TOLERANCE) | (np.linalg.det(views) < 0)
    if not bad.any():
        return None
    v = int(np.flatnonzero(bad)[0])
    at = f" (view {v})" if np.ndim(R) == 3 else ""
    return f"not a rotation{at}: |R Rᵀ - I| up to {off[v]:.3g}, det {np.linalg.det(views[v]):.6g}"


@dataclasses.dataclass
class Problem:
    """N keypoints of V views, views stored one after another.

    Shapes:
        view_offsets: (V+1,) int64, ``view_offsets[0] == 0``, last == N, non-decreasing.
        keypoints: (N, 2) float32 pixel (x, y).
        descriptors: (N, D) float32 raw descriptors.
        scales, orientations: (N,) float32 or None.
        K: (V, 3, 3) float64 intrinsics or None.
        R, t: (V, 3, 3), (V, 3) float64 world->camera pose (``x ~ K (R X + t)``) or None.
        image_size: (V, 2) int64 (width, height) or None.
        gt_track: (N,) int64 ground truth (>= 0 point id, -1 unmatched, -2 unlabelled) or None.
        camera_ids: (V,) tuple of str, the camera of every view (a window of a stream), or None.
            Lets per-stream state (:mod:`gcn_match_ros.stream`) follow a camera pair from one
            window to the next; not part of the ``.npz`` format.
    """

    view_offsets: np.ndarray
    keypoints: np.ndarray
    descriptors: np.ndarray
    scales: Optional[np.ndarray] = None
    orientations: Optional[np.ndarray] = None
    K: Optional[np.ndarray] = None
    R: Optional[np.ndarray] = None
    t: Optional[np.ndarray] = None
    image_size: Optional[np.ndarray] = None
    gt_track: Optional[np.ndarray] = None
    name: str = ""
    camera_ids: Optional[Tuple[str, ...]] = None

    def __post_init__(self) -> None:
        self.validate()

    # -- derived quantities -------------------------------------------------
    @property
    def n_views(self) -> int:
        return int(self.view_offsets.shape[0] - 1)

    @property
    def n_keypoints(self) -> int:
        return int(self.keypoints.shape[0])

    @property
    def view_sizes(self) -> np.ndarray:
        """(V,) int64 number of keypoints per view."""
        return np.diff(self.view_offsets)

    @property
    def view_index(self) -> np.ndarray:
        """(N,) int64 view of every keypoint."""
        return np.repeat(np.arange(self.n_views, dtype=np.int64), self.view_sizes)

    @property
    def has_poses(self) -> bool:
        return self.K is not None and self.R is not None and self.t is not None

    def view_slice(self, v: int) -> slice:
        return slice(int(self.view_offsets[v]), int(self.view_offsets[v + 1]))

    # -- validation -----------------------------------------------------------
    def validate(self) -> None:
        """Coerce dtypes and check every shape; raises :class:`FormatError` naming the key."""
        self.view_offsets = _as(self.view_offsets, np.int64, "view_offsets")
        _check_shape(self.view_offsets, (None,), "view_offsets")
        if self.view_offsets.shape[0] < 2:
            raise FormatError("'view_offsets': needs at least 2 entries (one view)")
        self.keypoints = _as(self.keypoints, np.float32, "keypoints")
        _check_shape(self.keypoints, (None, 2), "keypoints")
        n = self.keypoints.shape[0]
        vo = self.view_offsets
        if vo[0] != 0 or vo[-1] != n or np.any(np.diff(vo) < 0):
            raise FormatError(
                f"'view_offsets': must start at 0, be non-decreasing and end at N={n}, got {vo.tolist()}")
        self.descriptors = _as(self.descriptors, np.float32, "descriptors")
        _check_shape(self.descriptors, (n, None), "descriptors")
        if self.descriptors.shape[1] < 1:
            raise FormatError("'descriptors': descriptor dimension D must be >= 1")
        _check_finite(self.keypoints, "keypoints")
        _check_finite(self.descriptors, "descriptors")
        v = self.n_views
        specs = {
            "scales": (np.float32, (n,)),
            "orientations": (np.float32, (n,)),
            "K": (np.float64, (v, 3, 3)),
            "R": (np.float64, (v, 3, 3)),
            "t": (np.float64, (v, 3)),
            "image_size": (np.int64, (v, 2)),
            "gt_track": (np.int64, (n,)),
        }
        for key, (dtype, shape) in specs.items():
            val = getattr(self, key)
            if val is None:
                continue
            arr = _as(val, dtype, key)
            _check_shape(arr, shape, key)
            _check_finite(arr, key)
            setattr(self, key, arr)
        if (self.R is None) != (self.t is None):
            raise FormatError("'R' and 't' must be given together")
        # only magnitudes that make a solve meaningless: frames from a camera are also held to its
        # image (windowing.validate_frame); scenes made in code may project points past theirs
        for key, fault in (("keypoints", keypoint_range_fault(self.keypoints)),
                           ("descriptors", descriptor_range_fault(self.descriptors)),
                           ("K", intrinsics_fault(self.K) if self.K is not None else None),
                           ("R", rotation_fault(self.R) if self.R is not None else None)):
            if fault:
                raise FormatError(f"'{key}': {fault}")
        if self.gt_track is not None and np.any(self.gt_track < -2):
            raise FormatError("'gt_track': values must be >= -2")
        if self.camera_ids is not None:
            self.camera_ids = tuple(str(c) for c in self.camera_ids)
            if len(self.camera_ids) != v:
                raise FormatError(f"'camera_ids': expected {v} camera ids, got {len(self.camera_ids)}")

    # -- helpers --------------------------------------------------------------
    def subset_views(self, views) -> "Problem":
        """The problem restricted to ``views`` (in that order)."""
        views = [int(v) for v in views]
        idx = np.concatenate([np.arange(*self.view_slice(v).indices(self.n_keypoints)) for v in views]) \
            if views else np.zeros(0, np.int64)
        sizes = [self.view_sizes[v] for v in views]
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        per_kp = {k: getattr(self, k)[idx] if getattr(self, k) is not None else None
                  for k in ("keypoints", "descriptors", "scales", "orientations", "gt_track")}
        per_view = {k: getattr(self, k)[views] if getattr(self, k) is not None else None
                    for k in ("K", "R", "t", "image_size")}
        cams = tuple(self.camera_ids[v] for v in views) if self.camera_ids is not None else None
        return Problem(view_offsets=offsets, name=self.name, camera_ids=cams, **per_kp, **per_view)


_PROBLEM_REQUIRED = ("view_offsets", "keypoints", "descriptors")
_PROBLEM_OPTIONAL = ("scales", "orientations", "K", "R", "t", "image_size", "gt_track")


_UMASK = os.umask(0)  # read once at import (os.umask can only be read by setting it)
os.umask(_UMASK)


def atomic_write(path, write_fn) -> None:
    """Write a file via ``write_fn(tmp_path)`` then rename: readers never see a partial file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write_fn(tmp)
        # mkstemp makes the file private (0600); give it the mode a plain open() would
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _open_npz(path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise FormatError(f"{path}: no such file")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FormatError:
        raise
    except Exception as exc:  # zipfile / pickle refusal / truncated archive
        raise FormatError(f"{path}: not a readable .npz archive ({exc})") from None


def load_problem(path) -> Problem:
    """Read a problem file; raises :class:`FormatError` naming the bad key."""
    data = _open_npz(path)
    for key in _PROBLEM_REQUIRED:
        if key not in data:
            raise FormatError(f"{path}: missing required key '{key}'")
    kwargs = {k: data[k] for k in _PROBLEM_REQUIRED + _PROBLEM_OPTIONAL if k in data}
    try:
        return Problem(name=Path(path).stem, **kwargs)
    except FormatError as exc:
        raise FormatError(f"{path}: {exc}") from None


def save_problem(problem: Problem, path) -> None:
    problem.validate()
    arrays = {k: getattr(problem, k) for k in _PROBLEM_REQUIRED + _PROBLEM_OPTIONAL
              if getattr(problem, k) is not None}
    atomic_write(path, lambda tmp: _savez(tmp, arrays))


def _savez(tmp: str, arrays: dict) -> None:
    with open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


@dataclasses.dataclass
class Result:
    """A matcher's answer for one problem.

    Shapes:
        track: (N,) int64; same id >= 0 = matched, -1 = matched to nothing.
        pair_rows, pair_cols: (M,) int64 global indices, ``pair_rows < pair_cols``, different views.
        pair_scores: (M,) float32 in [0, 1].
        seconds: wall time of graph build + solve + rounding.
        method: method and settings, e.g. ``"gcn:default"``.
        timings: seconds per stage of the solve (:mod:`gcn_match_ros.timing`; they add up to
            about ``seconds``); not stored in result files.
    """

    track: np.ndarray
    pair_rows: np.ndarray
    pair_cols: np.ndarray
    pair_scores: np.ndarray
    seconds: float = 0.0
    method: str = ""
    timings: Dict[str, float] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        self.track = _as(self.track, np.int64, "track")
        _check_shape(self.track, (None,), "track")
        self.pair_rows = _as(self.pair_rows, np.int64, "pair_rows")
        self.pair_cols = _as(self.pair_cols, np.int64, "pair_cols")
        self.pair_scores = _as(self.pair_scores, np.float32, "pair_scores")
        m = self.pair_rows.shape[0] if self.pair_rows.ndim == 1 else -1
        for key in ("pair_rows", "pair_cols", "pair_scores"):
            _check_shape(getattr(self, key), (m if m >= 0 else None,), key)
        _check_finite(self.pair_scores, "pair_scores")
        if np.any(self.pair_rows >= self.pair_cols):
            raise FormatError("'pair_rows': must be < 'pair_cols' for every pair")
        if np.any(self.track < -1):
            raise FormatError("'track': values must be >= -1")
        self.seconds = float(self.seconds)
        self.method = str(self.method)

    def validate_against(self, problem: Problem) -> None:
        """Check sizes against ``problem`` and the at-most-one-keypoint-per-view-per-track rule."""
        n = problem.n_keypoints
        if self.track.shape[0] != n:
            raise FormatError(f"'track': expected shape ({n},), got {self.track.shape}")
        if self.pair_cols.size and (self.pair_cols.max() >= n or self.pair_rows.min() < 0):
            raise FormatError(f"'pair_rows'/'pair_cols': indices out of range [0, {n})")
        view = problem.view_index
        if self.pair_rows.size and np.any(view[self.pair_rows] == view[self.pair_cols]):
            raise FormatError("'pair_rows'/'pair_cols': pairs must join different views")
        m = self.track >= 0
        keys = self.track[m] * problem.n_views + view[m]
        if keys.size != np.unique(keys).size:
            raise FormatError("'track': a track holds two keypoints of one view (not cycle-consistent)")


_RESULT_KEYS = ("track", "pair_rows", "pair_cols", "pair_scores", "seconds", "method")


def load_result(path) -> Result:
    data = _open_npz(path)
    for key in _RESULT_KEYS:
        if key not in data:
            raise FormatError(f"{path}: missing required key '{key}'")
    try:
        return Result(track=data["track"], pair_rows=data["pair_rows"], pair_cols=data["pair_cols"],
                      pair_scores=data["pair_scores"], seconds=float(data["seconds"]),
                      method=str(data["method"]))
    except FormatError as exc:
        raise FormatError(f"{path}: {exc}") from None


def save_result(result: Result, path, extra: Optional[Dict[str, np.ndarray]] = None) -> None:
    """Write ``result`` (the format's keys) and ``extra`` keys beside them (e.g. a stream's
    ``landmark_ids``), which readers of the format ignore; an extra key may not replace one of
    the format's."""
    arrays = {"track": result.track, "pair_rows": result.pair_rows, "pair_cols": result.pair_cols,
              "pair_scores": result.pair_scores, "seconds": np.float64(result.seconds),
              "method": np.str_(result.method)}
    clash = sorted(set(extra or ()) & set(arrays))
    if clash:
        raise ValueError(f"extra result keys {clash} would replace the format's")
    arrays.update(extra or {})
    atomic_write(path, lambda tmp: _savez(tmp, arrays))
