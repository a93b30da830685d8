"""Problem files from the image folders with ground truth in ``shared/data``.

Three kinds of scene folder are read (``shared/data/README.md``):

- ``oxford/<scene>/``: ``img1.png`` … ``imgN.png`` and ``H1toNp`` homographies
  (``x_N ~ H1toN x_1``); kind ``'homography'``. ``homography/<scene>/`` is any other
  sequence in this layout (e.g. made by homography_sequence.py).
- ``strecha/<scene>/``: ``NNNN.png`` and ``NNNN.cam`` (``K``, ``R``, ``t`` lines,
  world→camera, ``x ~ K (R X + t)``); kind ``'poses'``.
- ``middlebury_temple/``: ``templeSR00NN.png`` and ``templeSR_par.txt``
  (``name k11..k33 r11..r33 t1 t2 t3``); kind ``'poses'``.

Features are OpenCV SIFT or ORB, keeping one keypoint per location (the strongest
response within 1.5 px: SIFT repeats a location once per orientation peak).

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
``benchmarks/results/photometric_labels_check.md``; :func:`make_problem` and :func:`convert`
use them with ``pose_labels="photometric"``):
each keypoint's depth by plane sweep against its neighbours in the window
(``plane_sweep.py``: NCC of a fronto-parallel patch, one clear peak), searched over the
depths of the window's :func:`label_poses` tracks (all ``-2`` with fewer than 5). Then as
on homography scenes: projections into view b link mutual nearest keypoints closer than
3 px where the patch also correlates with b at that depth (NCC ≥ 0.7: b sees it); a
keypoint not lifted, not seen by some view, or 3–10 px from a projection is ``-2``; else
``-1``.

Problem names are ``<scene>_<detector>_<views>``, e.g. ``oxford_graf_sift_123`` or
``strecha_fountain-P11_sift_4-5-6``: the image numbers of the window, joined without a
separator when all are one digit.
"""
from __future__ import annotations

import dataclasses
import itertools
import re
from pathlib import Path
from typing import Callable, Dict, List, NamedTuple, Optional, Sequence, Tuple

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from tqdm import tqdm

from .plane_sweep import SweepConfig, lift, patch_ncc
from .plane_sweep import project as plane_project
from .problem import Problem, save_problem

__all__ = ["DatasetError", "Scene", "Features", "read_oxford", "read_strecha", "read_middlebury",
           "load_scene", "available_scenes", "extract_features", "label_homography", "label_poses",
           "make_problem", "problem_name", "sample_windows", "convert"]

DETECTORS = ("sift", "orb")
POSE_LABELS = ("geometric", "photometric")
DEDUP_PX = 1.5
LINK_PX = 3.0  # homography scenes: a true pair is this close in the target image
IGNORE_PX = 10.0  # both kinds: closer than this but not linked -> unlabelled
EPIPOLAR_PX = 0.5  # pose scenes: epipolar tolerance of a pair (module docstring: why 0.5)
REPROJECT_PX = 0.5  # pose scenes: a confirming keypoint is this close to the reprojection
PHOTO_SEEN_NCC = 0.7  # photometric labels: a lifted patch correlates this well with a view seeing it


class DatasetError(ValueError):
    """A scene folder or ground-truth file is missing or malformed; the message names the file."""


@dataclasses.dataclass(frozen=True)
class Scene:
    """One scene: V images of a single dataset with their ground truth.

    Shapes:
        image_sizes: (V, 2) int64 (width, height).
        homographies: (V, 3, 3) float64, view v pixels -> view 0 pixels (homography scenes).
        K, R: (V, 3, 3) float64; t: (V, 3) float64, world->camera, ``x ~ K (R X + t)``
        (pose scenes).
    """

    name: str
    kind: str
    image_paths: Tuple[Path, ...]
    view_labels: Tuple[str, ...]
    image_sizes: np.ndarray
    homographies: Optional[np.ndarray] = None
    K: Optional[np.ndarray] = None
    R: Optional[np.ndarray] = None
    t: Optional[np.ndarray] = None

    @property
    def n_views(self) -> int:
        return len(self.image_paths)


class Features(NamedTuple):
    """Keypoints of one image, strongest response first.

    Shapes: keypoints (n, 2) float32 (x, y); descriptors (n, D) float32 (D = 128 SIFT,
    256 ORB bits as 0/1); scales (n,) float32 (OpenCV ``size``); orientations (n,)
    float32 radians.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray
    orientations: np.ndarray


# --------------------------------------------------------------------------------------
# Scene readers
# --------------------------------------------------------------------------------------
def _read_gray(path: Path) -> np.ndarray:
    """8-bit grayscale image (H, W); colour images are converted."""
    if not path.is_file():
        raise DatasetError(f"{path}: no such image")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DatasetError(f"{path}: not a readable image")
    return img


def _image_sizes(paths: Sequence[Path]) -> np.ndarray:
    """(V, 2) int64 (width, height) of every image."""
    return np.array([_read_gray(p).shape[::-1] for p in paths], dtype=np.int64).reshape(-1, 2)


def _numbers(path: Path, text: str, count: int, what: str) -> np.ndarray:
    """Parse exactly ``count`` finite floats from ``text``."""
    try:
        vals = np.array([float(tok) for tok in text.split()], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path}: {what}: expected {count} numbers, got {text.strip()!r}") from None
    if vals.size != count or not np.all(np.isfinite(vals)):
        raise DatasetError(f"{path}: {what}: expected {count} finite numbers, got {vals.size}")
    return vals


def _check_pose(path: Path, K: np.ndarray, R: np.ndarray) -> None:
    """Reject intrinsics that are not upper-triangular with positive focal lengths and
    rotations that are not orthonormal (the files print 6 decimals, hence the tolerance)."""
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and np.allclose(K[2], [0, 0, 1])):
        raise DatasetError(f"{path}: K is not an intrinsic matrix: {K.ravel().tolist()}")
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-3) and np.linalg.det(R) > 0):
        raise DatasetError(f"{path}: R is not a rotation matrix")


def _number_of(path: Path) -> str:
    """Image number from a file name ('img3.png' -> '3', '0004.png' -> '4'); the stem if none."""
    digits = re.findall(r"\d+", path.stem)
    return str(int(digits[-1])) if digits else path.stem


def read_oxford(folder: Path, dataset: str = "oxford") -> Scene:
    """``img1.png`` … ``imgN.png`` with ``H1to2p`` … ``H1toNp`` (``x_N ~ H1toN x_1``); the
    scene is named ``<dataset>_<folder name>``.

    Raises:
        DatasetError: missing images or homography files, or a file that is not a finite,
            invertible 3x3 matrix.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such scene folder")
    n = 0
    while (folder / f"img{n + 1}.png").is_file():
        n += 1
    if n < 2:
        raise DatasetError(f"{folder / 'img1.png'}: need img1.png and img2.png at least")
    paths = tuple(folder / f"img{v}.png" for v in range(1, n + 1))
    to_view0 = [np.eye(3)]
    for v in range(2, n + 1):
        path = folder / f"H1to{v}p"
        if not path.is_file():
            raise DatasetError(f"{path}: no such homography file")
        H = _numbers(path, path.read_text(), 9, "homography").reshape(3, 3)
        if abs(np.linalg.det(H)) < 1e-12:
            raise DatasetError(f"{path}: homography is singular")
        to_view0.append(np.linalg.inv(H))
    return Scene(name=f"{dataset}_{folder.name}", kind="homography", image_paths=paths,
                 view_labels=tuple(_number_of(p) for p in paths), image_sizes=_image_sizes(paths),
                 homographies=np.stack(to_view0))


def _read_cam(path: Path) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One Strecha ``.cam`` file: lines ``K`` (9 numbers), ``R`` (9), ``t`` (3); ``#`` comments."""
    fields: Dict[str, str] = {}
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        key, _, rest = line.partition(" ")
        if key not in ("K", "R", "t") or key in fields:
            raise DatasetError(f"{path}: unexpected line {line[:40]!r} (want one K, R and t line)")
        fields[key] = rest
    missing = [k for k in ("K", "R", "t") if k not in fields]
    if missing:
        raise DatasetError(f"{path}: missing line(s) {', '.join(missing)}")
    K = _numbers(path, fields["K"], 9, "K").reshape(3, 3)
    R = _numbers(path, fields["R"], 9, "R").reshape(3, 3)
    t = _numbers(path, fields["t"], 3, "t")
    _check_pose(path, K, R)
    return K, R, t


def read_strecha(folder: Path) -> Scene:
    """``NNNN.png`` with ``NNNN.cam`` (world->camera ``K``, ``R``, ``t``), in file-name order.

    Raises:
        DatasetError: no images, a missing or malformed ``.cam`` file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such scene folder")
    paths = tuple(sorted(p for p in folder.glob("*.png") if p.stem.isdigit()))
    if len(paths) < 2:
        raise DatasetError(f"{folder}: need at least two NNNN.png images")
    cams = []
    for p in paths:
        cam = p.with_suffix(".cam")
        if not cam.is_file():
            raise DatasetError(f"{cam}: no such camera file")
        cams.append(_read_cam(cam))
    K, R, t = (np.stack(x) for x in zip(*cams))
    return Scene(name=f"strecha_{folder.name}", kind="poses", image_paths=paths,
                 view_labels=tuple(_number_of(p) for p in paths), image_sizes=_image_sizes(paths),
                 K=K, R=R, t=t)


def read_middlebury(folder: Path, par_name: str = "templeSR_par.txt") -> Scene:
    """Middlebury multi-view stereo: ``<par_name>`` = count line, then per image
    ``name k11..k33 r11..r33 t1 t2 t3``; views in the file's order.

    Raises:
        DatasetError: missing or malformed parameter file, or an image it names is missing.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: no such scene folder")
    par = folder / par_name
    if not par.is_file():
        raise DatasetError(f"{par}: no such camera parameter file")
    lines = [ln for ln in par.read_text().splitlines() if ln.strip()]
    if not lines or not lines[0].strip().isdigit():
        raise DatasetError(f"{par}: first line must be the number of images")
    count = int(lines[0])
    if len(lines) - 1 != count or count < 2:
        raise DatasetError(f"{par}: header says {count} images, found {len(lines) - 1} lines "
                           "(need at least 2)")
    paths, Ks, Rs, ts = [], [], [], []
    for line in lines[1:]:
        name, _, rest = line.strip().partition(" ")
        vals = _numbers(par, rest, 21, f"image {name}")
        K, R, t = vals[:9].reshape(3, 3), vals[9:18].reshape(3, 3), vals[18:]
        _check_pose(par, K, R)
        path = folder / name
        if not path.is_file():
            raise DatasetError(f"{path}: image named in {par.name} is missing")
        paths.append(path)
        Ks.append(K)
        Rs.append(R)
        ts.append(t)
    return Scene(name=folder.name, kind="poses", image_paths=tuple(paths),
                 view_labels=tuple(_number_of(p) for p in paths), image_sizes=_image_sizes(paths),
                 K=np.stack(Ks), R=np.stack(Rs), t=np.stack(ts))


def load_scene(data_root: Path, scene: str) -> Scene:
    """A scene by its path under ``data_root``: ``oxford/<name>``, ``strecha/<name>``,
    ``middlebury_temple``, or ``homography/<name>`` (any sequence in the Oxford layout, e.g.
    one made by homography_sequence.py).

    Raises:
        DatasetError: unknown dataset or missing folder.
    """
    folder = Path(data_root) / scene
    dataset = Path(scene).parts[0] if Path(scene).parts else ""
    if dataset in ("oxford", "homography"):
        return read_oxford(folder, dataset)
    if dataset == "strecha":
        return read_strecha(folder)
    if dataset.startswith("middlebury"):
        return read_middlebury(folder)
    raise DatasetError(f"{folder}: unknown dataset {dataset!r} (expected oxford/<scene>, "
                       "strecha/<scene>, middlebury_temple or homography/<scene>)")


def available_scenes(data_root: Path) -> List[str]:
    """Scene ids under ``data_root`` accepted by :func:`load_scene`, sorted."""
    root = Path(data_root)
    ids = [f"{ds}/{p.name}" for ds in ("homography", "oxford", "strecha")
           for p in sorted((root / ds).glob("*")) if p.is_dir()]
    ids += [p.name for p in sorted(root.glob("middlebury*")) if p.is_dir()]
    return sorted(ids)


# --------------------------------------------------------------------------------------
# Features
# --------------------------------------------------------------------------------------
def _dedup(points: np.ndarray, order: np.ndarray, radius: float = DEDUP_PX) -> np.ndarray:
    """Greedy non-maximum suppression: walk ``order`` (strongest first), keep a point unless
    a kept one lies within ``radius``. Returns kept indices in walking order."""
    neighbours = cKDTree(points).query_ball_point(points, r=radius)
    suppressed = np.zeros(len(points), dtype=bool)
    kept = []
    for i in order:
        if suppressed[i]:
            continue
        kept.append(i)
        suppressed[neighbours[i]] = True
    return np.asarray(kept, dtype=np.int64)


def extract_features(image: np.ndarray, detector: str = "sift", max_features: int = 500) -> Features:
    """OpenCV SIFT or ORB, one keypoint per location (strongest response within 1.5 px).

    Ties between keypoints of one location (SIFT's orientation copies share their response)
    keep the first in OpenCV's output order, so the result is deterministic.

    Args:
        image: (H, W) uint8 grayscale or (H, W, 3) BGR.
        detector: 'sift' or 'orb'.
        max_features: passed to the detector (before de-duplication).
    """
    if detector not in DETECTORS:
        raise ValueError(f"detector must be one of {DETECTORS}, got {detector!r}")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    det = cv2.SIFT_create(max_features) if detector == "sift" else cv2.ORB_create(nfeatures=max_features)
    kps, desc = det.detectAndCompute(image, None)
    dim = 128 if detector == "sift" else 256
    if not kps:
        empty = np.zeros(0, np.float32)
        return Features(np.zeros((0, 2), np.float32), np.zeros((0, dim), np.float32), empty, empty)
    pts = np.array([k.pt for k in kps], dtype=np.float32)
    response = np.array([k.response for k in kps], dtype=np.float32)
    keep = _dedup(pts.astype(np.float64), np.argsort(-response, kind="stable"))
    if detector == "orb":
        desc = np.unpackbits(desc, axis=1)
    return Features(keypoints=pts[keep],
                    descriptors=desc[keep].astype(np.float32),
                    scales=np.array([kps[i].size for i in keep], dtype=np.float32),
                    orientations=np.deg2rad(np.array([kps[i].angle for i in keep], dtype=np.float32)))


# --------------------------------------------------------------------------------------
# Ground truth
# --------------------------------------------------------------------------------------
def _project(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Apply homography H (3, 3) to points (n, 2) -> (n, 2) float64."""
    h = np.c_[xy, np.ones(len(xy))] @ H.T
    return h[:, :2] / h[:, 2:]


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
        q_a = _project(H_ab, pts[a])
        ia, jb, d_ab = _mutual_links(q_a, _inside(q_a, image_sizes[b]), pts[b], link_px)
        rows.append(offsets[a] + ia)
        cols.append(offsets[b] + jb)
        near[offsets[a]:offsets[a + 1]] |= d_ab < ignore_px
    track = _tracks(n, view, np.concatenate(rows), np.concatenate(cols))
    track[(track == -1) & near] = -2
    return track


def _fundamental(K_a: np.ndarray, R_a: np.ndarray, t_a: np.ndarray,
                 K_b: np.ndarray, R_b: np.ndarray, t_b: np.ndarray) -> np.ndarray:
    """(3, 3) F with ``x_b^T F x_a = 0`` for world->camera poses; unit Frobenius norm."""
    R_ab = R_b @ R_a.T
    t_ab = t_b - R_ab @ t_a
    tx = np.array([[0, -t_ab[2], t_ab[1]], [t_ab[2], 0, -t_ab[0]], [-t_ab[1], t_ab[0], 0]])
    F = np.linalg.inv(K_b).T @ tx @ R_ab @ np.linalg.inv(K_a)
    return F / np.linalg.norm(F)


def _homog(xy: np.ndarray) -> np.ndarray:
    return np.c_[xy, np.ones(len(xy))]


def _epipolar_pairs(F: np.ndarray, x_a: np.ndarray, x_b: np.ndarray) -> np.ndarray:
    """(n,) for paired points (n, 2), (n, 2): the larger of the two point-to-epipolar-line
    distances, each in its own image's pixels."""
    h_a, h_b = _homog(x_a), _homog(x_b)
    l_b, l_a = h_a @ F.T, h_b @ F  # epipolar lines in b of x_a, in a of x_b
    alg = np.abs(np.sum(h_b * l_b, axis=1))
    return alg / np.minimum(np.hypot(l_b[:, 0], l_b[:, 1]), np.hypot(l_a[:, 0], l_a[:, 1]))


def _epipolar_matrix(F: np.ndarray, x_a: np.ndarray, x_b: np.ndarray) -> np.ndarray:
    """(n_a, n_b) :func:`_epipolar_pairs` for every pair of x_a (n_a, 2) and x_b (n_b, 2)."""
    h_a, h_b = _homog(x_a), _homog(x_b)
    l_b, l_a = h_a @ F.T, h_b @ F
    alg = np.abs(l_b @ h_b.T)
    return alg / np.minimum(np.hypot(l_b[:, 0], l_b[:, 1])[:, None], np.hypot(l_a[:, 0], l_a[:, 1])[None, :])


def _triangulate(P_a: np.ndarray, P_b: np.ndarray, u_a: np.ndarray, u_b: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of paired calibrated points.

    Shapes: P_a, P_b (3, 4) = [R | t]; u_a, u_b (m, 2) = first two entries of K^-1 [x, y, 1]
    -> (m, 3) world points (NaN/inf for points at infinity).
    """
    rows = [u_a[:, :1] * P_a[2] - P_a[0], u_a[:, 1:] * P_a[2] - P_a[1],
            u_b[:, :1] * P_b[2] - P_b[0], u_b[:, 1:] * P_b[2] - P_b[1]]
    X = np.linalg.svd(np.stack(rows, axis=1))[2][:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[:, :3] / X[:, 3:]


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
    F = {(a, b): _fundamental(K[a], R[a], t[a], K[b], R[b], t[b])
         for a, b in itertools.permutations(range(n_views), 2)}
    calib = [(_homog(p) @ np.linalg.inv(Kv).T)[:, :2] for p, Kv in zip(pts, K)]
    P = [np.c_[Rv, tv] for Rv, tv in zip(R, t)]
    trees = [cKDTree(p) for p in pts]
    near = np.zeros(n, dtype=bool)
    ambiguous = np.zeros(n, dtype=bool)
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for a, b in itertools.combinations(range(n_views), 2):
        if not (len(pts[a]) and len(pts[b])):
            continue
        D = _epipolar_matrix(F[a, b], pts[a], pts[b])
        near[offsets[a]:offsets[a + 1]] |= (D < ignore_px).any(axis=1)
        near[offsets[b]:offsets[b + 1]] |= (D < ignore_px).any(axis=0)
        i, j = np.nonzero(D <= epipolar_px)
        X = _triangulate(P[a], P[b], calib[a][i], calib[b][j])
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
                good = ((_epipolar_pairs(F[a, k], pts[a][i[m]], pts[k][cc]) <= epipolar_px)
                        & (_epipolar_pairs(F[b, k], pts[b][j[m]], pts[k][cc]) <= epipolar_px))
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
        return all(_epipolar_pairs(F[view[x], view[y]], kp[x][None], kp[y][None])[0] <= epipolar_px
                   for x, y in itertools.combinations(members, 2) if view[x] != view[y])

    track = _tracks(n, view, np.concatenate(rows), np.concatenate(cols), consistent=closes)
    track[ambiguous] = -2
    track[(track == -1) & near] = -2
    return track


def _window_depth_range(pts: Sequence[np.ndarray], K: np.ndarray, R: np.ndarray, t: np.ndarray,
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
    calib = [(_homog(kp[m]) @ np.linalg.inv(K[view[m[0]]]).T)[:, :2] for m in first.T]
    X = np.array([_triangulate(np.c_[R[view[a]], t[view[a]]], np.c_[R[view[b]], t[view[b]]],
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
    z_range = z_range or _window_depth_range(pts, K, R, t)
    if z_range is None:
        return np.full(n, -2, dtype=np.int64)
    lifted = [lift(images, K, R, t, a, pts[a], _sweep_support(a, n_views), z_range, sweep) for a in range(n_views)]
    near = np.zeros(n, dtype=bool)
    unknown = np.zeros(n, dtype=bool)  # whether a counterpart exists somewhere is not known
    rows, cols = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for a, b in itertools.permutations(range(n_views), 2):
        X, z = lifted[a]
        q_a = plane_project(K[b], R[b], t[b], X)
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


# --------------------------------------------------------------------------------------
# Problems
# --------------------------------------------------------------------------------------
FeatureCache = Dict[Tuple[Path, str, int], Features]


def _features(scene: Scene, v: int, detector: str, max_features: int,
              cache: Optional[FeatureCache]) -> Features:
    key = (scene.image_paths[v], detector, max_features)
    if cache is not None and key in cache:
        return cache[key]
    feats = extract_features(_read_gray(scene.image_paths[v]), detector, max_features)
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
            images = [_read_gray(scene.image_paths[v]).astype(np.float32) for v in views]
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
