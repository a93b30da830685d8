"""Scene folders of ``shared/data``: images with their ground-truth geometry.

Three kinds of scene folder are read (``shared/data/README.md``):

- ``oxford/<scene>/``: ``img1.png`` … ``imgN.png`` and ``H1toNp`` homographies
  (``x_N ~ H1toN x_1``); kind ``'homography'``. ``homography/<scene>/`` is any other
  sequence in this layout (e.g. made by :mod:`.homography_sequence`).
- ``strecha/<scene>/``: ``NNNN.png`` and ``NNNN.cam`` (``K``, ``R``, ``t`` lines,
  world→camera, ``x ~ K (R X + t)``); kind ``'poses'``.
- ``middlebury_temple/``: ``templeSR00NN.png`` and ``templeSR_par.txt``
  (``name k11..k33 r11..r33 t1 t2 t3``); kind ``'poses'``.
"""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import cv2
import numpy as np

from ..paths import CHECKOUT

__all__ = ["DATA_ROOT", "DatasetError", "Scene", "read_gray", "read_oxford", "read_strecha", "read_middlebury", "load_scene",
           "available_scenes"]

#: The scene folders of a checkout: ``shared/data`` beside the repository (the default root).
DATA_ROOT = CHECKOUT.parent / "shared" / "data"

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



def read_gray(path: Path) -> np.ndarray:
    """8-bit grayscale image (H, W); colour images are converted."""
    if not path.is_file():
        raise DatasetError(f"{path}: no such image")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise DatasetError(f"{path}: not a readable image")
    return img


def _image_sizes(paths: Sequence[Path]) -> np.ndarray:
    """(V, 2) int64 (width, height) of every image."""
    return np.array([read_gray(p).shape[::-1] for p in paths], dtype=np.int64).reshape(-1, 2)


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

