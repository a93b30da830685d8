"""Homography sequences made from one photograph: scenes in the Oxford layout with exact ground truth.

Each view is a perspective crop of the source image: view k of V (t = k / (V - 1)) maps its
rectangle onto a quadrilateral of the source that drifts, turns, grows or shrinks and skews
with t, so view 1 is a plain centred crop and the change grows along the sequence as in the
Oxford viewpoint sequences. Views 2… also get a photometric change (gain, gamma, optional
blur, noise). Every quadrilateral lies inside the source, so every view is fully covered.

:func:`write_sequence` writes ``img1.png`` … ``imgV.png`` and ``H1toNp`` (``x_N ~ H1toN x_1``)
— the layout :func:`.scenes.read_oxford` reads, so ``scenes.load_scene(root,
"homography/<name>")`` and :func:`.convert.convert` make problems of it labelled like Oxford.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, List, Tuple

import cv2
import numpy as np

__all__ = ["SequenceConfig", "source_image", "view_size", "view_quads", "homography_sequence", "write_sequence",
           "make_sequence"]


@dataclasses.dataclass(frozen=True)
class SequenceConfig:
    """How a sequence is drawn (defaults: benchmarks/results/orb_confirmation_protocol.md).

    Attributes:
        n_views: views per sequence (>= 2).
        long_side: the source is resized so its longer side has this many pixels.
        view_fraction: view size as a fraction of the source size.
        shift: drift of the quadrilateral's centre at t = 1, in view sizes.
        max_rotation_deg: rotation at t = 1 is uniform in ±this.
        zoom_range: the quadrilateral's scale at t = 1 is log-uniform in this range.
        corner_jitter: std of each corner's displacement at t = 1, in view sizes.
        gain_range, gamma_range: photometric change of views 2…: ``gain · I^gamma`` (I in [0, 1]).
        blur_probability, blur_sigma_range: chance of a Gaussian blur and its sigma (pixels).
        noise_sigma: additive Gaussian noise, grey levels.
        max_draws: draws of a sequence's geometry before giving up on keeping it inside the source.
    """

    n_views: int = 6
    long_side: int = 800
    view_fraction: float = 0.6
    shift: float = 0.08
    max_rotation_deg: float = 30.0
    zoom_range: Tuple[float, float] = (0.7, 1.5)
    corner_jitter: float = 0.12
    gain_range: Tuple[float, float] = (0.75, 1.25)
    gamma_range: Tuple[float, float] = (0.8, 1.25)
    blur_probability: float = 0.5
    blur_sigma_range: Tuple[float, float] = (0.5, 1.5)
    noise_sigma: float = 2.0
    max_draws: int = 100

    def __post_init__(self):
        if self.n_views < 2:
            raise ValueError(f"n_views must be >= 2, got {self.n_views}")
        if not 0 < self.view_fraction <= 1:
            raise ValueError(f"view_fraction must be in (0, 1], got {self.view_fraction}")
        if self.long_side < 16:
            raise ValueError(f"long_side must be >= 16, got {self.long_side}")


def source_image(image: np.ndarray, long_side: int) -> np.ndarray:
    """Grayscale uint8 (H, W) with its longer side resized to ``long_side`` (area averaging
    when shrinking, cubic when enlarging).

    Args:
        image: (H, W) or (H, W, 3) BGR, or (H, W, 4) BGRA, uint8.
    """
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise ValueError(f"image must be uint8 (H, W), (H, W, 3) or (H, W, 4), got {image.dtype} {image.shape}")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    h, w = image.shape
    scale = long_side / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC)


def view_size(source_size: Tuple[int, int], config: SequenceConfig) -> Tuple[int, int]:
    """(width, height) of every view: ``view_fraction`` of the source's, rounded."""
    return (max(2, round(source_size[0] * config.view_fraction)), max(2, round(source_size[1] * config.view_fraction)))


def _convex(quad: np.ndarray) -> bool:
    """(4, 2) corners in order form a convex quadrilateral (all turns one way)."""
    edges = np.roll(quad, -1, axis=0) - quad
    cross = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    return bool(np.all(cross > 0) or np.all(cross < 0))


def view_quads(source_size: Tuple[int, int], config: SequenceConfig, rng: np.random.Generator) -> np.ndarray:
    """Corners in the source of every view's rectangle, drawn until all lie inside the source.

    Args:
        source_size: (width, height) of the source.

    Returns:
        (V, 4, 2) float64: for each view, where its corners (0, 0), (w-1, 0), (w-1, h-1),
        (0, h-1) fall in the source (w, h = view size, :func:`view_size`).

    Raises:
        ValueError: no draw in ``config.max_draws`` stays inside the source.
    """
    W, H = source_size
    w, h = view_size(source_size, config)
    half = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=np.float64) * [(w - 1) / 2, (h - 1) / 2]
    centre = np.array([(W - 1) / 2, (H - 1) / 2])
    t = np.arange(config.n_views) / (config.n_views - 1)
    for _ in range(config.max_draws):
        rotation = np.deg2rad(rng.uniform(-config.max_rotation_deg, config.max_rotation_deg))
        log_zoom = rng.uniform(*np.log(config.zoom_range))
        direction = rng.uniform(0, 2 * np.pi)
        jitter = rng.standard_normal((config.n_views, 4, 2))
        quads = []
        for k, tk in enumerate(t):
            a = tk * rotation
            rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            corners = (half * np.exp(tk * log_zoom)) @ rot.T
            corners = corners + tk * config.corner_jitter * jitter[k] * [w, h]
            offset = tk * config.shift * np.array([w * np.cos(direction), h * np.sin(direction)])
            quads.append(corners + centre + offset)
        quads = np.stack(quads)
        inside = (quads[..., 0] >= 0).all() and (quads[..., 0] <= W - 1).all() and \
            (quads[..., 1] >= 0).all() and (quads[..., 1] <= H - 1).all()
        if inside and all(_convex(q) for q in quads):
            return quads
    raise ValueError(f"no sequence of {config.n_views} views stayed inside a {W}x{H} source in "
                     f"{config.max_draws} draws; lower zoom_range, max_rotation_deg or view_fraction")


def _photometric(view: np.ndarray, config: SequenceConfig, rng: np.random.Generator) -> np.ndarray:
    img = (view.astype(np.float64) / 255.0) ** rng.uniform(*config.gamma_range) * rng.uniform(*config.gain_range)
    if rng.random() < config.blur_probability:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(*config.blur_sigma_range))
    img = img * 255.0 + rng.normal(0.0, config.noise_sigma, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def homography_sequence(source: np.ndarray, config: SequenceConfig,
                        rng: np.random.Generator) -> Tuple[List[np.ndarray], np.ndarray]:
    """The views of one sequence and where their pixels lie in the source.

    Args:
        source: (H, W) uint8 grayscale (:func:`source_image`).

    Returns:
        views: V arrays (h, w) uint8; view 1 without photometric change.
        to_source: (V, 3, 3) float64, view pixel -> source pixel (``x_src ~ H x_view``).
    """
    if source.dtype != np.uint8 or source.ndim != 2:
        raise ValueError(f"source must be uint8 (H, W), got {source.dtype} {source.shape}")
    size = (source.shape[1], source.shape[0])
    w, h = view_size(size, config)
    rect = np.array([[0, 0], [w - 1, 0], [w - 1, h - 1], [0, h - 1]], dtype=np.float32)
    views, to_source = [], []
    for k, quad in enumerate(view_quads(size, config, rng)):
        H = cv2.getPerspectiveTransform(rect, quad.astype(np.float32)).astype(np.float64)
        # WARP_INVERSE_MAP: H maps view (destination) pixels to source pixels
        view = cv2.warpPerspective(source, H, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                   borderMode=cv2.BORDER_REPLICATE)
        views.append(view if k == 0 else _photometric(view, config, rng))
        to_source.append(H)
    return views, np.stack(to_source)


def write_sequence(folder: Path, views: List[np.ndarray], to_source: np.ndarray) -> Path:
    """Write ``img1.png`` … and ``H1toNp`` (view 1 pixel -> view N pixel) into ``folder``.

    Returns:
        ``folder``.
    """
    if len(views) != len(to_source) or len(views) < 2:
        raise ValueError(f"need >= 2 views and one homography each, got {len(views)} and {len(to_source)}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for k, view in enumerate(views, start=1):
        if not cv2.imwrite(str(folder / f"img{k}.png"), view):
            raise OSError(f"{folder / f'img{k}.png'}: could not write")
    for k in range(2, len(views) + 1):
        H = np.linalg.inv(to_source[k - 1]) @ to_source[0]
        (folder / f"H1to{k}p").write_text("\n".join(" ".join(f"{v:.17g}" for v in row) for row in H / H[2, 2]) + "\n")
    return folder


def make_sequence(folder: Path, read_image: Callable[[], np.ndarray], rng: np.random.Generator,
                  config: SequenceConfig = SequenceConfig()) -> Path:
    """One photograph's sequence in ``folder`` (:func:`source_image`, :func:`homography_sequence`,
    :func:`write_sequence`), made once: a folder that already holds the sequence's last
    homography is kept, and ``read_image`` (the photograph, any image ``cv2.imread`` gives) is
    then not called.

    Returns:
        ``folder``.
    """
    folder = Path(folder)
    if (folder / f"H1to{config.n_views}p").is_file():
        return folder
    views, to_source = homography_sequence(source_image(read_image(), config.long_side), config, rng)
    return write_sequence(folder, views, to_source)
