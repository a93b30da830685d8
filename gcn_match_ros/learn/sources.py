"""Where training problems come from: a :class:`DataSource` is any callable
``source(start=0) -> Iterator[Problem]``.

- :class:`ProblemFileSource` cycles over ``.npz`` problem files;
- :class:`SyntheticSource` generates scenes (:mod:`gcn_match_ros.data.synthetic`);
- :class:`gcn_match_ros.bags.source.BagSource` serves the windows of rosbag2 bags;
- :class:`InterleavedSource` takes several in turn, :class:`ShardedSource` gives one
  distributed rank its share;
- :func:`data_source` builds one from command-line data specs (files, bags, ``synth:...``).
"""
from __future__ import annotations

import functools
import glob
from itertools import islice
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Optional, Protocol, Sequence, Tuple, Union

import numpy as np

from ..bags.source import BAG_SUFFIXES, BagSource, check_disjoint_scenes, is_bag_path
from ..data import synthetic
from ..problem import Problem, load_problem

__all__ = ["DataSource", "ProblemFileSource", "SyntheticSource", "ShardedSource", "InterleavedSource",
           "data_source", "check_disjoint", "SYNTH_VAL_SEED"]

#: Validation scenes never share a seed with training scenes (``data_source(train=False)``).
SYNTH_VAL_SEED = 1_000_003


class DataSource(Protocol):
    """Where training problems come from: ``source(start=0) -> Iterator[Problem]``.

    The iterator yields the stream of problems from position ``start`` on (0 = the
    beginning). :func:`train` calls ``source(start)`` once per run, with ``start`` =
    the number of problems already consumed when resuming, so a seekable source
    makes a resumed run see exactly the problems an uninterrupted one would. A
    source that cannot seek may ignore ``start`` (a resumed run then sees other
    problems, which is harmless). Training sources should be infinite (cycle or
    generate); a validation source only needs ``TrainConfig.val_size`` problems.
    """

    def __call__(self, start: int = 0) -> Iterator[Problem]: ...


class ProblemFileSource:
    """Cycles over ``.npz`` problem files (:func:`problem.load_problem`).

    Args:
        paths: files, or directories whose ``*.npz`` files are used (sorted).
        shuffle: visit the files in a new random order every epoch (seeded).
        seed: seed of the shuffling; epoch e uses ``default_rng([seed, e])``.
        cycle: repeat forever (training) or stop after one pass (evaluation).
        cache: keep loaded problems in memory.
    """

    seekable = True

    def __init__(self, paths: Union[str, Path, Sequence[Union[str, Path]]], shuffle: bool = True,
                 seed: int = 0, cycle: bool = True, cache: bool = True) -> None:
        if isinstance(paths, (str, Path)):
            paths = [paths]
        files: List[Path] = []
        for p in map(Path, paths):
            if p.is_dir():
                files.extend(sorted(p.glob("*.npz")))
            elif p.is_file():
                files.append(p)
            else:
                raise ValueError(f"ProblemFileSource: {p}: no such file or directory")
        if not files:
            raise ValueError(f"ProblemFileSource: no problem files in {[str(p) for p in paths]}")
        self.files, self.shuffle, self.seed, self.cycle = files, shuffle, seed, cycle
        self._cache: Optional[Dict[Path, Problem]] = {} if cache else None

    def __len__(self) -> int:
        return len(self.files)

    def _load(self, path: Path) -> Problem:
        if self._cache is None:
            return load_problem(path)
        if path not in self._cache:
            self._cache[path] = load_problem(path)
        return self._cache[path]

    def _order(self, epoch: int) -> np.ndarray:
        n = len(self.files)
        return np.random.default_rng([self.seed, epoch]).permutation(n) if self.shuffle else np.arange(n)

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        n = len(self.files)
        k = int(start)
        while self.cycle or k < n:
            epoch, pos = divmod(k, n)
            yield self._load(self.files[self._order(epoch)[pos]])
            k += 1


class SyntheticSource:
    """An endless stream of generated problems.

    Problem k is ``generator_fn(np.random.default_rng([seed, k]))``, so the stream is
    reproducible and seekable (``start`` costs nothing).

    Args:
        generator_fn: ``(rng: np.random.Generator) -> Problem``.
        seed: stream seed (use different seeds for training and validation).
        length: stop after this many problems (None = endless).
    """

    seekable = True

    def __init__(self, generator_fn: Callable[[np.random.Generator], Problem], seed: int = 0,
                 length: Optional[int] = None) -> None:
        self.generator_fn, self.seed, self.length = generator_fn, seed, length

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        k = int(start)
        while self.length is None or k < self.length:
            yield self.generator_fn(np.random.default_rng([self.seed, k]))
            k += 1


class ShardedSource:
    """Rank ``rank``'s disjoint share of a stream split among ``world_size`` ranks.

    Local problem j is problem ``j * world_size + rank`` of ``source``, so local problems
    ``[s, s + n)`` of all ranks together are exactly problems ``[s·W, (s + n)·W)`` of the
    source: distributed training with per-rank batch B sees the problems a single process
    with batch B·W would. Seekable sources (``seekable = True``) are indexed directly;
    other sources are read in full and thinned.
    """

    def __init__(self, source: DataSource, rank: int, world_size: int) -> None:
        if world_size < 1 or not 0 <= rank < world_size:
            raise ValueError(f"ShardedSource: need 0 <= rank < world_size, got rank={rank}, world_size={world_size}")
        self.source, self.rank, self.world_size = source, int(rank), int(world_size)
        self.seekable = bool(getattr(source, "seekable", False))

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        W, r = self.world_size, self.rank
        if not self.seekable:
            yield from islice(self.source(int(start) * W + r), 0, None, W)
            return
        j = int(start)
        while True:
            try:
                yield next(iter(self.source(j * W + r)))
            except StopIteration:
                return
            j += 1


class InterleavedSource:
    """Several sources taken in turn: problem k is problem ``k // G`` of source ``k % G``
    (seekable when every source is); a finite source that runs out is skipped."""

    def __init__(self, sources: Sequence[DataSource]) -> None:
        if not sources:
            raise ValueError("InterleavedSource: no sources")
        self.sources = list(sources)
        self.seekable = all(getattr(s, "seekable", False) for s in self.sources)

    def __call__(self, start: int = 0) -> Iterator[Problem]:
        G, start = len(self.sources), int(start)
        firsts = [start + (g - start) % G for g in range(G)]  # first index >= start of each source
        iters: Dict[int, Iterator[Problem]] = {g: iter(self.sources[g](firsts[g] // G)) for g in range(G)}
        g = start % G
        while iters:
            it = iters.get(g)
            if it is not None:
                try:
                    yield next(it)
                except StopIteration:
                    del iters[g]
            g = (g + 1) % G



def _synthetic_source(spec: str, seed: int) -> SyntheticSource:
    parts = spec.split(":")
    usage = (f"use synth:PRESET[:VIEWS[:DESCRIPTOR]] with PRESET one of {', '.join(synthetic.PRESETS)} and "
             f"DESCRIPTOR one of {', '.join(synthetic.DESCRIPTOR_KINDS)}")
    if len(parts) not in (2, 3, 4):
        raise ValueError(f"bad data spec '{spec}': {usage}")
    try:
        views = int(parts[2]) if len(parts) >= 3 else 3
    except ValueError:
        views = 0
    if views < 2:
        raise ValueError(f"bad data spec '{spec}': VIEWS must be an integer >= 2")
    kind = parts[3] if len(parts) == 4 else "sift"
    try:
        config = synthetic.preset(parts[1], views, kind)
    except ValueError as exc:
        raise ValueError(f"bad data spec '{spec}': {exc}; {usage}") from None
    source = SyntheticSource(functools.partial(synthetic.random_scene_problem, config), seed=seed)
    source.description = f"synthetic {parts[1]} scenes, {views} views, {kind} descriptors"  # type: ignore[attr-defined]
    return source


def _expand_specs(specs: Sequence[str]) -> Tuple[List[Path], List[Path], List[str]]:
    """Data specs -> (problem files, bags, synth specs)."""
    npz: List[Path] = []
    bag_paths: List[Path] = []
    synth: List[str] = []
    for spec in specs:
        if spec.startswith("synth:"):
            synth.append(spec)
            continue
        hits = sorted(glob.glob(spec)) if any(ch in spec for ch in "*?[") else [spec]
        if not hits:
            raise ValueError(f"no file matches '{spec}'")
        for h in map(Path, hits):
            if not h.exists():
                raise ValueError(f"{h}: no such file or directory")
            if is_bag_path(h):
                bag_paths.append(h)
            elif h.is_dir():
                problems = sorted(h.glob("*.npz"))
                bagged = sorted(q for q in h.iterdir() if is_bag_path(q))
                if not problems and not bagged:
                    raise ValueError(f"{h}: directory holds no problem files (*.npz) or bags "
                                     f"({', '.join('*' + s for s in BAG_SUFFIXES)}, rosbag2 folders)")
                npz.extend(problems)
                bag_paths.extend(bagged)
            elif h.suffix == ".npz":
                npz.append(h)
            else:
                raise ValueError(f"{h}: not a problem file (.npz), a bag (.mcap, .db3, rosbag2 folder) "
                                 f"or synth:PRESET[:VIEWS[:DESCRIPTOR]]")
    return npz, bag_paths, synth


def data_source(specs: Sequence[str], seed: int = 0, train: bool = True) -> DataSource:
    """A :class:`DataSource` from command-line data specs.

    Forms: problem files or globs (``data/*.npz``) or folders of them ->
    :class:`ProblemFileSource`; bags (``.mcap``, ``.db3``, rosbag2 folders, folders of bags)
    -> :class:`BagSource`; ``synth:PRESET[:VIEWS[:DESCRIPTOR]]`` (``synth:rome16k:4``,
    ``synth:partial:3:binary`` for ORB-like codes) -> :class:`SyntheticSource`. Several
    kinds are taken in turn (:class:`InterleavedSource`).
    ``train=False`` (validation): one pass, no repetition, and synthetic scenes from a
    seed range training never uses. The result has a ``description`` attribute.

    Raises:
        ValueError: unknown form, missing files, unreadable bags.
    """
    npz, bag_paths, synth = _expand_specs(specs)
    sources: List[Any] = []
    words: List[str] = []
    if npz:
        sources.append(ProblemFileSource(npz, shuffle=True, seed=seed, cycle=train))
        words.append(f"{len(npz)} problem file(s)")
    if bag_paths:
        bs = BagSource(bag_paths, shuffle=True, seed=seed, cycle=train)
        sources.append(bs)
        words.append(bs.describe())
    for spec in synth:
        s = _synthetic_source(spec, seed if train else seed + SYNTH_VAL_SEED)
        sources.append(s)
        words.append(s.description)  # type: ignore[attr-defined]
    if not sources:
        raise ValueError("no data given")
    src = sources[0] if len(sources) == 1 else InterleavedSource(sources)
    src.description = "; ".join(words)  # type: ignore[union-attr]
    src.parts = sources  # type: ignore[union-attr]
    return src


def check_disjoint(train_src: Any, val_src: Any) -> None:
    """Refuse training and validation data that share problem files or bag scenes."""
    parts_t = getattr(train_src, "parts", [train_src])
    parts_v = getattr(val_src, "parts", [val_src])
    files_t = {p.resolve() for s in parts_t if isinstance(s, ProblemFileSource) for p in s.files}
    files_v = {p.resolve() for s in parts_v if isinstance(s, ProblemFileSource) for p in s.files}
    if files_t & files_v:
        raise ValueError(f"{len(files_t & files_v)} problem file(s) are in both --train and --val, "
                         f"e.g. {sorted(files_t & files_v)[0]}")
    for bt in (s for s in parts_t if isinstance(s, BagSource)):
        for bv in (s for s in parts_v if isinstance(s, BagSource)):
            check_disjoint_scenes(bt, bv)

