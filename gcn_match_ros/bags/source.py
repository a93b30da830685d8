"""Training problems from rosbag2 bags: the windows the matcher node would form on replay.

Core module (numpy, rosbags through :mod:`gcn_match_ros.bags`; never rclpy).

:class:`BagSource` reads each bag once (:func:`.contents.read_bag`), feeds its frames in bag
order to a :class:`~gcn_match_ros.windowing.WindowAssembler` exactly as the matcher node does
(:meth:`.contents.BagContents.windows`), and turns every window into a :class:`Problem`
(:func:`~gcn_match_ros.windowing.window_problem`): keypoints, descriptors, scales, orientations, K from
``camera_info``, world->camera R, t from ``/<cam>/pose`` (so the epipolar loss applies
to posed bags) and ``gt_track`` from ``/<cam>/gt_labels`` (:func:`.contents.window_labels`).
The windows are then served like :class:`gcn_match_ros.learn.sources.ProblemFileSource` serves files: an
endless, seeded, per-epoch shuffled and seekable stream.

Validation must use *other scenes* than training (consecutive windows of one scene share
images): :func:`bag_scene` names a bag's scene (from ``KeypointLabels.source``, e.g.
``oxford/graf``, else the file name), :func:`split_by_scene` splits bag paths by scene,
and :func:`check_disjoint_scenes` refuses overlapping train/val sets.
"""
from __future__ import annotations

import posixpath
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from ..problem import Problem
from ..windowing import WindowConfig, window_problem
from .contents import BagContents, read_bag, window_labels

__all__ = ["BagSource", "BAG_SUFFIXES", "is_bag_path", "bag_files", "bag_scene", "split_by_scene",
           "check_disjoint_scenes"]

#: File suffixes of single-file bags (a rosbag2 *directory* has a ``metadata.yaml``).
BAG_SUFFIXES = (".mcap", ".db3")

PathLike = Union[str, Path]


def is_bag_path(path: PathLike) -> bool:
    """A ``.mcap`` / ``.db3`` file or a rosbag2 directory (with ``metadata.yaml``)."""
    p = Path(path)
    return p.suffix.lower() in BAG_SUFFIXES or (p.is_dir() and (p / "metadata.yaml").is_file())


def bag_files(paths: Union[PathLike, Sequence[PathLike]]) -> List[Path]:
    """Expand bag paths: files and rosbag2 directories as given; any other directory
    contributes its ``*.mcap`` / ``*.db3`` files and rosbag2 sub-directories (sorted).

    Raises:
        ValueError: a path that does not exist, or a directory without bags.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out: List[Path] = []
    for p in map(Path, paths):
        if not p.exists():
            raise ValueError(f"{p}: no such bag file or directory")
        if p.is_dir() and not (p / "metadata.yaml").is_file():
            found = sorted(q for q in p.iterdir()
                           if (q.is_file() and q.suffix.lower() in BAG_SUFFIXES)
                           or (q.is_dir() and (q / "metadata.yaml").is_file()))
            if not found:
                raise ValueError(f"{p}: directory holds no bags (*.mcap, *.db3 or rosbag2 folders)")
            out.extend(found)
        else:
            out.append(p)
    return out


def _scene_of(contents: BagContents) -> str:
    for srcs in contents.sources.values():
        for s in srcs:
            if s:
                d = posixpath.dirname(s.replace("\\", "/"))
                if d:
                    return d
    name = contents.path.name
    for suf in BAG_SUFFIXES:
        if name.lower().endswith(suf):
            name = name[: -len(suf)]
    return name


def bag_scene(path: PathLike) -> str:
    """The scene a bag shows: the folder of the images named in ``KeypointLabels.source``
    (``oxford/graf/img1.png`` -> ``oxford/graf``); bags without it: the file name without suffix."""
    return _scene_of(read_bag(path, progress=False))


def split_by_scene(paths: Union[PathLike, Sequence[PathLike]], val_scenes: Optional[Sequence[str]] = None,
                   val_fraction: float = 0.25, seed: int = 0) -> Tuple[List[Path], List[Path]]:
    """Split bags into (train, val) so that no scene is in both.

    Args:
        val_scenes: the scenes held out (as :func:`bag_scene` names them); None = a seeded
            random ``val_fraction`` of the scenes (at least one, and at least one left for training).

    Raises:
        ValueError: fewer than two scenes, or a ``val_scenes`` entry that no bag shows.
    """
    files = bag_files(paths)
    scene = {p: bag_scene(p) for p in files}
    names = sorted(set(scene.values()))
    if len(names) < 2:
        raise ValueError(f"split_by_scene: need bags of at least two scenes, got {names}")
    if val_scenes is None:
        k = min(max(1, int(round(val_fraction * len(names)))), len(names) - 1)
        chosen = set(np.random.default_rng(seed).permutation(names)[:k].tolist())
    else:
        chosen = set(val_scenes)
        missing = chosen - set(names)
        if missing:
            raise ValueError(f"split_by_scene: no bag shows scene(s) {sorted(missing)}; scenes: {names}")
    return [p for p in files if scene[p] not in chosen], [p for p in files if scene[p] in chosen]


def check_disjoint_scenes(train: "BagSource", val: "BagSource") -> None:
    """Raise ``ValueError`` when a scene is in both sources (validation must use other scenes)."""
    both = sorted(set(train.scenes) & set(val.scenes))
    if both:
        raise ValueError(f"scene(s) {both} are in both the training and the validation bags; "
                         f"validate on bags of other scenes")


class BagSource:
    """Cycles over the matching windows of rosbag2 bags (a :class:`gcn_match_ros.learn.sources.DataSource`).

    Problem k of the stream is window ``order(epoch)[pos]`` with ``epoch, pos = divmod(k, n)``
    over the n windows of all bags (bags in the given order, windows in emission order);
    ``source(start)`` starts at problem ``start`` (seekable, costs nothing).

    Args:
        paths: bag files (``.mcap``, ``.db3``), rosbag2 directories, or directories of bags.
        window_config: the matcher node's window settings; None = the defaults
            (:class:`~gcn_match_ros.windowing.WindowConfig`) with the cameras of each bag (natural order).
        shuffle: new seeded random window order every epoch (``default_rng([seed, epoch])``).
        seed: seed of the shuffling.
        cycle: repeat forever (training) or stop after one pass (validation, evaluation).
        min_views: skip windows with fewer views (None = keep every window the node forms).
        progress: tqdm bars while reading (None = only for large bags).

    Attributes:
        files: the bags; scenes: scene of each bag (:func:`bag_scene`);
        problems: the windows as problems (name ``<bag stem>:<window index>``);
        window_frames: (bag index, [(camera id, stamp ns), ...]) of every window;

    Raises:
        ValueError (:class:`.io.BagError` included): unreadable bag, a bag without windows,
        or descriptor dimensions that differ between bags.
    """

    seekable = True

    def __init__(self, paths: Union[PathLike, Sequence[PathLike]], window_config: Optional[WindowConfig] = None,
                 shuffle: bool = True, seed: int = 0, cycle: bool = True, min_views: Optional[int] = None,
                 progress: Optional[bool] = None) -> None:
        self.files = bag_files(paths)
        self.window_config, self.shuffle, self.seed, self.cycle = window_config, shuffle, seed, cycle
        self.scenes: List[str] = []
        self.problems: List[Problem] = []
        self.window_frames: List[Tuple[int, List[Tuple[str, float]]]] = []
        dims: Dict[int, Path] = {}
        for b, path in enumerate(self.files):
            contents = read_bag(path, progress=progress)
            self.scenes.append(_scene_of(contents))
            config = window_config or WindowConfig(cameras=tuple(contents.cameras))
            n_before = len(self.problems)
            for frames, labels in contents.windows(config):
                if min_views is not None and len(frames) < min_views:
                    continue
                problem = window_problem(frames, name=f"{_stem(path)}:{len(self.problems) - n_before}")
                if labels is not None:
                    problem.gt_track = window_labels(labels)
                    problem.validate()
                self.problems.append(problem)
                self.window_frames.append((b, [(f.camera_id, f.stamp_ns) for f in frames]))
                dims.setdefault(problem.descriptors.shape[1], path)
            if len(self.problems) == n_before:
                raise ValueError(f"{path}: no matching windows with cameras {list(config.cameras)} "
                                 f"(the bag has {contents.cameras}); check the window settings")
        if len(dims) > 1:
            raise ValueError("bags with different descriptor dimensions cannot be mixed: "
                             + ", ".join(f"D={d} ({p.name})" for d, p in sorted(dims.items())))

    @property
    def descriptor_dim(self) -> int:
        return int(self.problems[0].descriptors.shape[1])

    @property
    def has_poses(self) -> bool:
        """True when every window has K, R, t (the epipolar loss applies to all of them)."""
        return all(p.has_poses for p in self.problems)

    def __len__(self) -> int:
        return len(self.problems)

    def _order(self, epoch: int) -> np.ndarray:
        n = len(self.problems)
        return np.random.default_rng([self.seed, epoch]).permutation(n) if self.shuffle else np.arange(n)

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        n = len(self.problems)
        k = int(start)
        order_epoch, order = -1, None
        while self.cycle or k < n:
            epoch, pos = divmod(k, n)
            if epoch != order_epoch:
                order_epoch, order = epoch, self._order(epoch)
            yield self.problems[order[pos]]
            k += 1

    def describe(self) -> str:
        posed = sum(p.has_poses for p in self.problems)
        return (f"{len(self.problems)} windows from {len(self.files)} bag(s) of scene(s) "
                f"{sorted(set(self.scenes))}, {posed} with poses")


def _stem(path: Path) -> str:
    name = path.name
    return name[: -len(path.suffix)] if path.suffix.lower() in BAG_SUFFIXES else name
