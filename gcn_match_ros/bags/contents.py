"""Keypoint frames in rosbag2 bags: the topic layout, written and read, formed into windows.

Core module: uses ``rosbags`` and numpy only (never rclpy), so the trainer, the
evaluator and the tests read bags exactly as recorded, and the matcher node's windows
(:meth:`BagContents.windows`) are the ones it forms on replay.

Topic layout (per camera ``<cam>``, e.g. ``cam0``; all stamps are image stamps)
-------------------------------------------------------------------------------
- ``/<cam>/keypoints`` (``gcn_match_msgs/msg/Keypoints``): keypoints + descriptors of one
  image, ``camera_info`` embedded; ``header.frame_id = "<cam>_optical_frame"``.
- ``/<cam>/camera_info`` (``sensor_msgs/msg/CameraInfo``): the same calibration, same
  stamp (all-zero ``k``: uncalibrated).
- ``/<cam>/pose`` (``geometry_msgs/msg/PoseStamped``): pose of ``<cam>_optical_frame`` in
  ``world`` (only frames with R, t, e.g. scenes with poses).
- ``/<cam>/gt_labels`` (``gcn_match_msgs/msg/KeypointLabels``): scene-global ground truth
  per keypoint (bags made from dataset scenes).

The messages of one frame share ``header.stamp`` and the bag's log time equals that
stamp, so the bag's order is stamp order (what a live rig publishes).

Pose convention
---------------
``/<cam>/pose`` is the camera's optical frame (z forward, x right, y down) expressed in
``world``: ``header.frame_id = "world"``, ``position`` = camera centre ``C`` and
``orientation`` = the rotation ``R_wc`` taking camera coordinates to world
coordinates (camera->world, the usual tf convention). The problem format
(``shared/spec/problem-format.md``) uses world->camera ``R, t`` with
``x ~ K (R X + t)``; the two are related by::

    R = R_wc^T,   t = -R_wc^T C        (pose -> problem: :func:`gcn_match_ros.geometry.pose_to_rt`)
    R_wc = R^T,   C = -R^T t           (problem -> pose: :func:`gcn_match_ros.geometry.rt_to_pose`)

Labels
------
``KeypointLabels.labels[i]`` labels keypoint ``i`` of the Keypoints message with the
same camera and stamp: ``>= 0`` id of the imaged scene point, ``-1`` no partner in any
other image of the scene, ``-2`` unlabelled. A dataset scene is labelled *once over all
its images* (:mod:`gcn_match_ros.data.labels`), so ids are
consistent across every frame of the bag and any window can be scored. Within one window
an id that occurs once has no partner there: :func:`window_labels` maps it to ``-1``
(equivalent for pair scoring, and what ``gt_track`` means in a problem file).

Sample bags: :mod:`.make` (a dataset scene as a rig of cameras sliding along its images).
"""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Dict, Iterator, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import numpy as np
from tqdm import tqdm

from ..geometry import pose_msg_to_rt
from ..stamps import ns_to_seconds, stamp_to_ns
from ..problem import Problem
from ..windowing import Frame, WindowAssembler, WindowConfig, kept_rows, window_problem
from .codec import camera_info_msg, frame_from_keypoints_msg, header_msg, keypoints_msg, pose_msg
from .io import BagError, BagReader, BagWriter
from .typesys import CAMERA_INFO_TYPE, KEYPOINTS_TYPE, LABELS_TYPE, POSE_TYPE

__all__ = ["BagContents", "ReplayWindows", "write_scene_bag", "read_bag", "bag_windows", "window_labels"]


def write_scene_bag(path, frames_by_camera: Mapping[str, Sequence[Frame]],
                    labels: Optional[Mapping[str, Sequence[Optional[np.ndarray]]]] = None, *,
                    storage: str = "mcap", label_method: str = "",
                    sources: Optional[Mapping[str, Sequence[str]]] = None,
                    compress: bool = True, progress: bool = False) -> Path:
    """Write frames (and optional labels) as a bag in the layout of the module docstring.

    Everything per frame comes from the :class:`Frame`: ``stamp_ns`` (header stamp and log
    time), ``frame_id`` (default ``<cam>_optical_frame``), ``K`` and ``image_size``
    (``camera_info``, embedded and on ``/<cam>/camera_info``), ``R, t`` (world->camera;
    written as the camera->world ``/<cam>/pose``, only for frames that have them), the
    descriptors as :func:`.codec.keypoints_fields` encodes them.

    Args:
        path: ``*.mcap`` -> a single mcap file; else a rosbag2 directory of ``storage``.
        frames_by_camera: camera id -> frames in stamp order (topic namespace = camera id).
        labels: camera id -> per-frame (N,) int labels (scene-global ids, -1, -2) or None,
            parallel to ``frames_by_camera``; published on ``/<cam>/gt_labels``.
        label_method, sources: ``KeypointLabels.method`` and per-frame ``.source`` strings.

    Returns:
        ``path``. The bag appears there only once complete (written aside, then renamed).
    """
    items = []
    for order, (cam, frames) in enumerate(frames_by_camera.items()):
        cam_labels = (labels or {}).get(cam)
        cam_sources = (sources or {}).get(cam)
        for i, f in enumerate(frames):
            if f.camera_id != cam:
                raise ValueError(f"frame {i} of camera {cam!r} has camera_id {f.camera_id!r}")
            lab = cam_labels[i] if cam_labels is not None else None
            if lab is not None and len(lab) != f.count:
                raise ValueError(f"labels of {cam} frame {i}: {len(lab)} values for {f.count} keypoints")
            items.append((int(f.stamp_ns), order, f, lab, cam_sources[i] if cam_sources else ""))
    items.sort(key=lambda x: (x[0], x[1]))
    with BagWriter(path, storage, compress) as bag:
        T = bag.store.types
        for ns, _, f, lab, src in tqdm(items, desc=f"writing {Path(path).name}", unit="frame",
                                       disable=not progress):
            cam = f.camera_id
            if not f.frame_id:
                f = dataclasses.replace(f, frame_id=f"{cam}_optical_frame")
            header = header_msg(T, ns, f.frame_id)
            bag.write(f"/{cam}/camera_info", CAMERA_INFO_TYPE, ns, camera_info_msg(T, header, f.K, f.image_size))
            if f.R is not None and f.t is not None:
                bag.write(f"/{cam}/pose", POSE_TYPE, ns,
                          pose_msg(T, ns, f.R, f.t))
            if lab is not None:
                bag.write(f"/{cam}/gt_labels", LABELS_TYPE, ns, T[LABELS_TYPE](
                    header=header, camera_id=cam, labels=np.asarray(lab, dtype=np.int64),
                    method=label_method, source=src))
            bag.write(f"/{cam}/keypoints", KEYPOINTS_TYPE, ns, keypoints_msg(f, bag.store))
    return Path(path)



@dataclasses.dataclass
class BagContents:
    """Frames of a bag.

    Attributes:
        path: the bag.
        topics: topic -> message type; counts: topic -> messages.
        frames: camera id -> frames (Keypoints messages) in bag order, with K, image_size and,
            when the bag has ``<ns>/pose`` at the same stamp, R, t (world->camera).
        labels: camera id -> per-frame (N,) int64 labels or None, parallel to ``frames``.
        sources: camera id -> per-frame ``KeypointLabels.source`` ("" if none).
        order: (camera id, index) of every frame in bag (log-time) order: the order a
            player publishes them, and the order :meth:`windows` feeds the assembler.
    """

    path: Path
    topics: Dict[str, str]
    counts: Dict[str, int]
    frames: Dict[str, List[Frame]]
    labels: Dict[str, List[Optional[np.ndarray]]]
    sources: Dict[str, List[str]]
    order: List[Tuple[str, int]]

    @property
    def cameras(self) -> List[str]:
        """Camera ids, natural order (cam2 before cam10)."""
        return sorted(self.frames, key=lambda c: [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", c)])

    @property
    def n_frames(self) -> int:
        return len(self.order)

    def frames_in_order(self) -> Iterator[Frame]:
        for cam, i in self.order:
            yield self.frames[cam][i]

    def labels_of(self, frame: Frame) -> Optional[np.ndarray]:
        """Labels of a frame of this bag (looked up by camera id and stamp)."""
        return self._index().get((frame.camera_id, frame.stamp_ns), (None, None))[1]

    def _index(self) -> Dict[Tuple[str, int], Tuple[Frame, Optional[np.ndarray]]]:
        idx = getattr(self, "_idx", None)
        if idx is None:
            idx = {(f.camera_id, f.stamp_ns): (f, self.labels[c][i])
                   for c, fs in self.frames.items() for i, f in enumerate(fs)}
            object.__setattr__(self, "_idx", idx)
        return idx

    def windows(self, config: WindowConfig, flush: bool = True
                ) -> Iterator[Tuple[List[Frame], Optional[np.ndarray]]]:
        """Feed the frames to a :class:`WindowAssembler` in bag order, as the matcher node
        does on replay (``add(frame)``; stamps in the past never hit ``max_future``), and
        yield each window's frames (validated copies, views in ``config.cameras`` order)
        with their labels concatenated in the same rows as ``window_problem(frames)``
        ((N,) int64 scene-global labels, or None when a frame has none). ``flush``: also
        emit what is left at the end of the bag."""
        assembler = WindowAssembler(config)
        for frame in self.frames_in_order():
            for window in assembler.add(frame):
                yield window, self._window_labels(window, config)
        if flush:
            for window in assembler.flush():
                yield window, self._window_labels(window, config)

    def replay_windows(self, config: Optional[WindowConfig] = None) -> "ReplayWindows":
        """The windows the matcher node forms when this bag is replayed into it, as problems:
        what an offline run must solve, in order, to reproduce the node's output
        (:func:`gcn_match_ros.stream.solve_stream`).

        Args:
            config: the node's window parameters; None: its defaults with the bag's cameras.
        """
        config = config or WindowConfig(cameras=tuple(self.cameras))
        frames, labels = [], []
        for window, labelled in self.windows(config, flush=False):  # the node never flushes
            frames.append(window)
            labels.append(labelled)
        return ReplayWindows(frames=frames, problems=[window_problem(w) for w in frames], labels=labels,
                             stamps_ns=[max(f.stamp_ns for f in w) for w in frames])

    def _window_labels(self, window: Sequence[Frame], config: WindowConfig) -> Optional[np.ndarray]:
        parts = []
        idx = self._index()
        for f in window:
            orig, lab = idx.get((f.camera_id, f.stamp_ns), (None, None))
            if lab is None or orig is None:
                return None
            if orig.count != f.count:  # the assembler kept max_keypoints of them: same rows
                lab = lab[kept_rows(orig.count, orig.scores, config.max_keypoints)]
            parts.append(np.asarray(lab, dtype=np.int64))
        return np.concatenate(parts) if parts else np.zeros(0, np.int64)


class ReplayWindows(NamedTuple):
    """A bag's windows as the matcher node forms them (:meth:`BagContents.replay_windows`).

    Attributes:
        frames: per window its frames (views in camera order); problems: the same stacked
            (``camera_ids`` set); labels: per window (N,) scene-global labels or None;
        stamps_ns: per window its newest view stamp (the node's window stamp).
    """

    frames: List[List[Frame]]
    problems: List[Problem]
    labels: List[Optional[np.ndarray]]
    stamps_ns: List[int]


def window_labels(labels: np.ndarray) -> np.ndarray:
    """Scene-global labels of one window -> the window's ``gt_track``: ids >= 0 that occur
    only once in the window become -1 (their partners are outside the window)."""
    labels = np.asarray(labels, dtype=np.int64)
    out = labels.copy()
    pos = labels >= 0
    if pos.any():
        ids, counts = np.unique(labels[pos], return_counts=True)
        single = np.isin(labels, ids[counts == 1]) & pos
        out[single] = -1
    return out


def read_bag(path, progress: Optional[bool] = None) -> BagContents:
    """Read every Keypoints frame of a bag with its pose and labels.

    Frames come from topics of type Keypoints (camera id = ``Keypoints.camera_id``, else the
    topic's namespace). A ``PoseStamped`` topic in the same namespace (``/<cam>/pose``)
    with the same stamp gives the frame's R, t (converted to world->camera); a
    ``KeypointLabels`` message with the same camera id and stamp gives its labels.

    Args:
        progress: tqdm bar; None = only for bags of more than 500 messages.

    Raises:
        BagError: missing, truncated or corrupt bag, a malformed Keypoints or PoseStamped message,
            or labels that do not fit their frame.
    """
    with BagReader(path) as r:
        info = r.info()
        show = info.message_count > 500 if progress is None else progress
        frames: Dict[str, List[Frame]] = {}
        order: List[Tuple[str, int]] = []
        ns_of: Dict[Tuple[str, int], str] = {}  # (camera, stamp ns) -> topic namespace
        frame_ns: Dict[Tuple[str, int], Tuple[str, int]] = {}
        poses: Dict[Tuple[str, int], Tuple[np.ndarray, np.ndarray]] = {}
        labels: Dict[Tuple[str, int], Tuple[np.ndarray, str]] = {}
        wanted = {t for t, ty in info.topics.items() if ty in (KEYPOINTS_TYPE, LABELS_TYPE, POSE_TYPE)}
        bar = tqdm(total=info.message_count, desc=f"reading {Path(path).name}", unit="msg", disable=not show)
        with bar:
            for topic, msgtype, _, raw in r.messages(sorted(wanted)):
                bar.update(1)
                ns = topic.rsplit("/", 1)[0]
                if msgtype == KEYPOINTS_TYPE:
                    msg = r.decode(raw, msgtype)
                    try:
                        frame = frame_from_keypoints_msg(msg, camera_id=str(msg.camera_id) or ns.strip("/") or topic)
                    except ValueError as exc:  # counts that do not fit the arrays
                        raise BagError(f"{path}: malformed Keypoints message on {topic} at "
                                       f"{ns_to_seconds(stamp_to_ns(msg.header.stamp)):.9f}: {exc}") from None
                    cam = frame.camera_id or ns.strip("/") or topic
                    if frame.camera_id != cam:
                        frame = dataclasses.replace(frame, camera_id=cam)
                    stamp_ns = frame.stamp_ns
                    lst = frames.setdefault(cam, [])
                    frame_ns[(cam, stamp_ns)] = (cam, len(lst))
                    order.append((cam, len(lst)))
                    ns_of[(cam, stamp_ns)] = ns
                    lst.append(frame)
                elif msgtype == POSE_TYPE:
                    msg = r.decode(raw, msgtype)
                    try:
                        poses[(ns, stamp_to_ns(msg.header.stamp))] = pose_msg_to_rt(msg.pose)
                    except ValueError as exc:  # a NaN position, an all-zero quaternion
                        raise BagError(f"{path}: malformed PoseStamped message on {topic} at "
                                       f"{ns_to_seconds(stamp_to_ns(msg.header.stamp)):.9f}: {exc}") from None
                else:
                    msg = r.decode(raw, msgtype)
                    labels[(str(msg.camera_id), stamp_to_ns(msg.header.stamp))] = (
                        np.asarray(msg.labels, dtype=np.int64).copy(), str(msg.source))
            bar.update(info.message_count - bar.n)
    out_labels = {c: [None] * len(fs) for c, fs in frames.items()}
    out_sources = {c: [""] * len(fs) for c, fs in frames.items()}
    for key, (cam, i) in frame_ns.items():
        pose = poses.get((ns_of[key], key[1]))
        if pose is not None:
            frames[cam][i] = dataclasses.replace(frames[cam][i], R=pose[0], t=pose[1])
        lab = labels.get(key)
        if lab is not None:
            if len(lab[0]) != frames[cam][i].count:
                raise BagError(f"{path}: labels of {cam} at {ns_to_seconds(key[1]):.9f} have {len(lab[0])} "
                               f"values for {frames[cam][i].count} keypoints")
            out_labels[cam][i], out_sources[cam][i] = lab
    return BagContents(path=Path(path), topics=info.topics, counts=info.counts, frames=frames,
                       labels=out_labels, sources=out_sources, order=order)


def bag_windows(path, window_config: WindowConfig, progress: Optional[bool] = None
                ) -> Iterator[Tuple[List[Frame], Optional[np.ndarray]]]:
    """The windows of a bag, formed by :class:`WindowAssembler` exactly as the matcher node
    forms them on replay: ``(frames, labels)`` per window (see :meth:`BagContents.windows`;
    ``windowing.window_problem(frames)`` stacks them, ``labels`` has the same rows)."""
    yield from read_bag(path, progress=progress).windows(window_config)

