"""The experiment protocol the benchmark scripts (``benchmarks/*.py``) share.

- The split of the real scenes: which windows train the shipped models (:data:`TRAIN_SCENES`,
  images < :data:`SPLIT_AT`), which validate them (images >= :data:`SPLIT_AT`) and which are
  never touched (Strecha castle-P19 and every Oxford scene, the held-out test):
  :func:`images_of`, :func:`split`, :func:`role`, :func:`problem_files`; the fixed subsample
  of benchmark windows, :func:`windows`.
- The generated scenes standing in for each detector's descriptors: :data:`SYNTHETIC_DESCRIPTORS`
  (the descriptor kind of each detector is :data:`gcn_match_ros.detect.DETECTOR_KINDS`).
- The pose-scene label checks (``label_chance.py``, ``photometric_labels_check.py``): their
  windows :data:`WINDOWS`, the loop over them :func:`pose_windows` and the count
  :func:`first_pair_tracks`.
- Reporting: the header every results file starts with (:func:`results_header`: title, the
  command that ran, the machine), writing the file (:func:`write_results`), the machine's speed
  when a timing ran (:func:`speed_note`; with when and for how long: :func:`run_note`) and the F1
  lead of gcn over the best other method with a bootstrap interval (:func:`lead_lines`).

Problem names follow :func:`gcn_match_ros.data.convert.problem_name`:
``<dataset>_<scene>_<detector>_<views>``, e.g. ``strecha_fountain-P11_sift_4-5-6``.
A core module: it never imports ROS (rclpy, :mod:`gcn_match_ros.ros`).
"""
from __future__ import annotations

import os
import platform
import shlex
import sys
import time
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from .data.convert import convert, make_problem
from .data.scenes import DATA_ROOT, Scene, load_scene, read_gray
from .detect import Features, extract_features
from .metrics import count_pairs, paired_bootstrap
from .paths import CHECKOUT
from .problem import Problem, Result
from .revision_solve import solve_at_revision, split_revision

__all__ = ["DATA_ROOT", "TRAIN_SCENES", "SPLIT_AT", "SYNTHETIC_DESCRIPTORS", "WINDOWS", "GEOMETRIC_DEV_SCENES",
           "GEOMETRIC_HELD_OUT_SCENES", "spaced_windows", "geometric_validation_problems", "images_of", "split", "role",
           "windows", "problem_files", "first_pair_tracks", "pose_windows", "lead_lines", "cpu_name",
           "describe_machine", "command_line", "results_header", "write_results", "python_speed", "speed_note",
           "run_note", "resident_memory_mb", "solved_at_revision"]


#: Scenes the shipped models are trained on (Strecha windows only below :data:`SPLIT_AT`).
TRAIN_SCENES = ["strecha/fountain-P11", "strecha/entry-P10", "middlebury_temple"]
#: Strecha windows with every image < SPLIT_AT train, every image >= SPLIT_AT validate.
SPLIT_AT = 6
#: The generated scenes' descriptors standing in for each detector's
#: (``descriptor_kind`` of :class:`gcn_match_ros.data.synthetic.SceneConfig`).
SYNTHETIC_DESCRIPTORS = {"sift": "sift", "orb": "binary"}
#: Pose scenes of the geometric evaluation (``benchmarks/geometric_eval.py``): the ones the
#: shipped models saw in training (their windows are where precision is developed) and the one
#: never used (castle-P19: checked, never tuned on).
GEOMETRIC_DEV_SCENES = ("strecha/fountain-P11", "strecha/entry-P10", "middlebury_temple")
GEOMETRIC_HELD_OUT_SCENES = ("strecha/castle-P19",)
#: Windows (view numbers) of the pose-scene label checks; those past a scene's last view are skipped.
WINDOWS = ((0, 1, 2), (6, 7, 8), (0, 1, 2, 3), (6, 7, 8, 9), (0, 1, 2, 3, 4, 5))


def spaced_windows(n_views: int, sizes: Sequence[int] = (3, 4, 5, 6, 7, 8), spacings: Sequence[int] = (1, 2, 3),
                   starts: Optional[int] = 2, first: int = 0) -> List[Tuple[int, ...]]:
    """Windows of every ``size`` taking every ``spacing``-th view of views ``first`` ..
    ``n_views - 1`` of a sequence, like the cameras of a rig pointing different ways (wider
    spacing: less overlap).

    ``starts`` windows per (size, spacing), spread evenly over the positions where the window
    fits (first and last position for 2; None: every position); sizes that do not fit give none.

    Returns:
        View index tuples, e.g. (0, 2, 4) for size 3, spacing 2.
    """
    out = []
    for spacing in spacings:
        for size in sizes:
            last = n_views - 1 - (size - 1) * spacing
            if last < first:
                continue
            positions = (range(first, last + 1) if starts is None
                         else np.linspace(first, last, max(1, starts)).round().astype(int).tolist())
            for start in sorted(set(positions)):
                out.append(tuple(range(start, start + size * spacing, spacing)))
    return out


def geometric_validation_problems(data_root: Union[str, Path], detector: str,
                                  max_features: int = 500) -> List[Problem]:
    """The windows a model's threshold is chosen on by geometric precision: every
    :func:`spaced_windows` position over the validation images (>= :data:`SPLIT_AT`) of the
    Strecha :data:`TRAIN_SCENES`, with cameras and pose labels."""
    out = []
    for name in TRAIN_SCENES:
        if not name.startswith("strecha/"):
            continue
        scene = load_scene(Path(data_root), name)
        cache: dict = {}
        for views in spaced_windows(scene.n_views, starts=None, first=SPLIT_AT):
            out.append(make_problem(scene, views, detector, max_features, cache))
    return out


def images_of(name: str) -> List[int]:
    """The image numbers of a problem's window, read back from its name.

    Args:
        name: a problem name (or file stem), e.g. ``oxford_graf_sift_123`` or
            ``strecha_fountain-P11_sift_7-8-9-10``.

    Returns:
        The numbers in window order, e.g. ``[1, 2, 3]``, ``[7, 8, 9, 10]``.
    """
    tail = name.rsplit("_", 1)[1]
    return [int(x) for x in (tail.split("-") if "-" in tail else list(tail))]


def split(files: Sequence[Path]) -> Tuple[List[Path], List[Path]]:
    """Training and validation problem files of the shipped models.

    Held-out test scenes (castle-P19, every Oxford scene) are dropped; Strecha windows go to
    training when every image is < :data:`SPLIT_AT`, to validation when every image is >= it,
    nowhere when they straddle it; other scenes (Middlebury temple) train.

    Args:
        files: problem files (``.npz``) named by :func:`gcn_match_ros.data.convert.problem_name`.

    Returns:
        (train, val): the files of each part, in the order given.
    """
    parts = [role(Path(f).stem) for f in files]
    return ([f for f, r in zip(files, parts) if r == "train"], [f for f, r in zip(files, parts) if r == "val"])


def role(name: str) -> str:
    """A problem's part of the split (the one rule :func:`split` applies): ``'test'`` (Oxford,
    castle-P19: never trained on), ``'train'`` (other non-Strecha scenes, i.e. the temple, and
    Strecha windows below :data:`SPLIT_AT`), ``'val'``, or ``'train/val overlap'`` (a Strecha
    window straddling :data:`SPLIT_AT`, used for neither)."""
    if name.startswith("oxford") or "castle" in name:
        return "test"
    if not name.startswith("strecha"):
        return "train"
    ims = images_of(name)
    return "train" if max(ims) < SPLIT_AT else ("val" if min(ims) >= SPLIT_AT else "train/val overlap")


def windows(names: Sequence[str], quick: bool) -> List[str]:
    """The fixed subsample of windows the real-scene benchmarks score.

    Oxford 123, 234, 1234, 123456 (the dev windows); Strecha one window per size starting at
    images 0 and 6 (castle also 12); ``quick``: one 3-view window per scene (Oxford 123,
    Strecha starting at 0).

    Args:
        names: problem names.
        quick: the small subset.

    Returns:
        The kept names, in the order given.
    """
    keep = []
    for n in names:
        ims = images_of(n)
        if n.startswith("oxford"):
            ok = n.rsplit("_", 1)[1] in (("123",) if quick else ("123", "234", "1234", "123456"))
        else:
            starts = (0,) if quick else ((0, 6, 12) if "castle" in n else (0, 6))
            ok = ims[0] in starts and (len(ims) == 3 or not quick)
        if ok:
            keep.append(n)
    return keep


def problem_files(data: Union[str, Path], data_root: Union[str, Path], detector: str) -> List[Path]:
    """The real problem files of :data:`TRAIN_SCENES` for ``detector``.

    Made with :func:`gcn_match_ros.data.convert.convert` (500 keypoints, windows of 3, 4 and 6
    consecutive views) when the folder holds none.

    Args:
        data: the problem folder; empty: ``/tmp/real_gcn/train_<detector>``.
        data_root: the scene folders (:data:`DATA_ROOT` in a checkout).
        detector: ``'sift'`` or ``'orb'``.

    Returns:
        The folder's ``.npz`` files, sorted (split them with :func:`split`).
    """
    folder = Path(data or f"/tmp/real_gcn/train_{detector}")
    if not list(folder.glob("*.npz")):
        convert(Path(data_root), folder, TRAIN_SCENES, sizes=(3, 4, 6), detectors=(detector,), max_features=500)
    return sorted(folder.glob("*.npz"))


def first_pair_tracks(gt: np.ndarray, n0: int, n1: int) -> int:
    """Pairs labelled true between a window's first two views.

    Args:
        gt: (N,) int track labels of the window's keypoints, view by view (>= 0: a track;
            -1 / -2: none / unlabelled).
        n0: keypoints of view 0 (the first ``n0`` entries); n1: of view 1 (the next ``n1``).

    Returns:
        The number of tracks with a member in both views.
    """
    a, b = gt[:n0], gt[n0:n0 + n1]
    return len(np.intersect1d(a[a >= 0], b[b >= 0]))


def pose_windows(root: Path, scenes: Sequence[str], windows: Sequence[Sequence[int]], detector: str,
                 features: int) -> Iterator[Tuple[str, Scene, List[int], List[Tuple[Features, np.ndarray]]]]:
    """Every window that fits each pose scene, with its views' keypoints and images.

    Each image is read and its features extracted once per scene.

    Args:
        root: the scene folders (:data:`DATA_ROOT`).
        scenes: scene ids, e.g. ``"strecha/castle-P19"``.
        windows: view numbers of each window (e.g. :data:`WINDOWS`); windows past a scene's
            last view are skipped.
        detector: ``'sift'`` or ``'orb'``; features: keypoints per view.

    Yields:
        (scene id, Scene, window as a list, views): per window view its
        :class:`~gcn_match_ros.detect.Features` and (H, W) uint8 grey image.
    """
    for name in scenes:
        scene = load_scene(root, name)
        cache = {}
        for win in windows:
            if max(win) >= scene.n_views:
                continue
            for v in win:
                if v not in cache:
                    image = read_gray(scene.image_paths[v])
                    cache[v] = (extract_features(image, detector, features), image)
            yield name, scene, list(win), [cache[v] for v in win]


def solved_at_revision(method: str, problems: Sequence[Problem]) -> List[Result]:
    """Every problem solved by ``method`` = ``SPEC@REVISION``, the package as it was at that git
    revision (:func:`gcn_match_ros.revision_solve.solve_at_revision`), for a benchmark table that
    needs every window: a refusal stops the benchmark, naming it (SystemExit).
    """
    spec, revision = split_revision(method)
    print(f"{method}: solving {len(problems)} windows with the package at {revision}", flush=True)
    results = solve_at_revision(spec, revision, problems)
    refused = [r for r in results if isinstance(r, Exception)]
    if refused:
        raise SystemExit(f"{method} refused {len(refused)} of {len(problems)} windows: {refused[0]}")
    return results


def lead_lines(rep: Dict, problems: Sequence, subsets: Dict[str, Sequence[str]]) -> List[str]:
    """Markdown lines: the first gcn method's F1 lead over the best other method.

    The rival is the non-gcn method with the best mean F1 among those that solved every
    problem; the lead is the mean difference over windows with a 95% paired bootstrap
    interval (:func:`gcn_match_ros.metrics.paired_bootstrap`), for all problems and for each
    subset, with the labelled true pairs of each.

    Args:
        rep: a report of :func:`gcn_match_ros.evaluation.evaluate` on ``problems``.
        problems: the scored problems.
        subsets: label -> problem names (subsets of ``problems``).

    Returns:
        The lines (a heading and one per subset); none when there is no gcn method or no rival.
    """
    names = [p.name for p in problems]
    full = {spec: e for spec, e in rep["methods"].items()
            if not e.get("reference") and all(n in e["per_problem"] for n in names)}
    gcn = [spec for spec in full if spec.startswith("gcn")]
    if not gcn:
        return []
    f1 = {spec: np.array([e["per_problem"][n]["F1"] for n in names]) for spec, e in full.items()}
    rivals = [spec for spec in full if not spec.startswith("gcn")]
    if not rivals:
        return []
    rival = max(rivals, key=lambda spec: f1[spec].mean())
    true_pairs = {p.name: count_pairs(p.gt_track, p.view_index)[1] for p in problems}
    lines = [f"\nF1 lead of {full[gcn[0]]['describe']} over the best other method, {full[rival]['describe']} "
             "(mean over windows; 95% bootstrap interval over windows):\n"]
    for label, ns in [("all", names)] + list(subsets.items()):
        idx = [names.index(n) for n in ns]
        if not idx:
            continue
        mean, lo, hi = paired_bootstrap(f1[gcn[0]][idx], f1[rival][idx])
        lines.append(f"- {label}: {mean:+.3f} [{lo:+.3f}, {hi:+.3f}], {len(idx)} windows, "
                     f"{sum(true_pairs[n] for n in ns)} labelled true pairs")
    return lines


def cpu_name() -> str:
    """The CPU model (``/proc/cpuinfo``'s model name), else ``platform.processor()`` or 'unknown'."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def describe_machine(torch_threads: Union[None, int, str] = None, extra: Sequence[str] = ()) -> str:
    """One line describing the machine a result was measured on.

    Args:
        torch_threads: torch's intra-op threads as the script set them (e.g. ``1`` or
            ``"1 per run"``); given, the torch version is named too; None: torch not mentioned.
        extra: further items appended (e.g. the load average).

    Returns:
        E.g. ``nproc=2, CPU: AMD EPYC, Python 3.11.7, torch 2.13.0+cpu, torch threads 1``; nproc
        counts the cores this process may run on (and the machine's, when fewer).
    """
    total = os.cpu_count()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else total
    parts = [f"nproc={usable}" + (f" of {total} CPUs" if usable != total else ""), f"CPU: {cpu_name()}",
             f"Python {platform.python_version()}"]
    if torch_threads is not None:
        import torch

        parts.append(f"torch {torch.__version__}, torch threads {torch_threads}")
    return ", ".join(parts + list(extra))


def command_line(script: Union[str, Path], argv: Optional[Sequence[str]] = None, launcher: str = ".venv/bin/python",
                 env: Sequence[str] = ()) -> str:
    """The shell command that ran a script, to repeat it.

    Args:
        script: the script's path (``__file__``); shown relative to the repository when inside it.
        argv: its arguments; None: ``sys.argv[1:]``.
        launcher: what ran it, e.g. ``.venv/bin/python`` or ``./run.sh python``.
        env: names of environment variables shown before the command when set (e.g.
            ``OPENBLAS_NUM_THREADS``).

    Returns:
        E.g. ``.venv/bin/python benchmarks/real_eval.py --quick``.

    Raises:
        ValueError: an ``env`` entry that is not a bare name (``NAME=value`` would never be shown).
    """
    bad = [k for k in env if not k.isidentifier()]
    if bad:
        raise ValueError(f"env takes variable names, got {bad}")
    path = Path(script).resolve()
    shown = path.relative_to(CHECKOUT) if path.is_relative_to(CHECKOUT) else Path(script)
    args = list(sys.argv[1:] if argv is None else argv)
    prefix = [f"{k}={shlex.quote(os.environ[k])}" for k in env if k in os.environ]
    return " ".join(prefix + [launcher, shlex.join([str(shown)] + [str(a) for a in args])])


def python_speed() -> float:
    """Seconds a fixed pure-Python loop (10⁷ integer additions) takes now: the machine's speed at
    the time of a timing run. This project's 2-core machine drifts within minutes, more than many
    changes move a benchmark (this loop 0.37-0.59 s within an hour), so timing tables state it. A
    coarse indicator: numeric code has also slowed while this loop did not."""
    start = time.perf_counter()
    total = 0
    for i in range(10_000_000):
        total += i
    return time.perf_counter() - start


def resident_memory_mb(pid: Optional[int] = None) -> float:
    """Resident memory of process ``pid`` (None: this one) in MB, from Linux's /proc; nan where it
    cannot be read (another system, a process gone)."""
    try:
        with open(f"/proc/{'self' if pid is None else int(pid)}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError):
        pass
    return float("nan")


def speed_note(before: float, after: float) -> str:
    """The sentence a timing table gives the machine's speed with: :func:`python_speed` before and
    after the run."""
    return (f"A fixed pure-Python loop (experiments.python_speed) took {before:.2f} s before the run and "
            f"{after:.2f} s after it (lower is faster).")


def run_note(seconds: float, speed_before: float) -> str:
    """The line under a timing table's header: when it ran, for how long, and the machine's speed
    before and after (:func:`speed_note`; call it as the run ends)."""
    return f"Run {time.strftime('%Y-%m-%d %H:%M')}, {seconds:.0f} s. {speed_note(speed_before, python_speed())}"


def results_header(title: str, script: Union[str, Path], argv: Optional[Sequence[str]] = None,
                   torch_threads: Union[None, int, str] = None, machine_extra: Sequence[str] = (),
                   launcher: str = ".venv/bin/python", env: Sequence[str] = ()) -> List[str]:
    """The first lines of a results file: title, command, machine.

    Args:
        title: the heading (without ``#``).
        script, argv, launcher, env: as :func:`command_line`.
        torch_threads, machine_extra: as :func:`describe_machine` (``torch_threads``, ``extra``).

    Returns:
        Markdown lines ``# title``, blank, ``Command: `...` `` and ``Machine: ...`` (each ending
        in a markdown line break); the script's own notes follow.
    """
    return [f"# {title}\n", f"Command: `{command_line(script, argv, launcher, env)}`  ",
            f"Machine: {describe_machine(torch_threads, machine_extra)}  "]


def write_results(out: Union[str, Path], text: str, append: bool = False) -> Path:
    """Write a results file's ``text`` to ``out``, making its folder, and say where.

    Args:
        append: keep what ``out`` holds and put ``text`` after it, below a rule (``---``), as the
            earlier runs of a results file stand below the latest.

    Returns:
        ``out`` as a path.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if append and out.is_file():
        text = out.read_text().rstrip("\n") + "\n\n---\n\n" + text
    out.write_text(text)
    print(f"written to {out}")
    return out
