"""Descriptors as the matcher compares them: row normalisation and the descriptor kind.

A descriptor kind is ``(dimension, binary)``: SIFT is ``(128, False)``, ORB ``(256, True)``
(32 bytes unpacked to 0/1 columns, as ``shared/spec/problem-format.md`` stores bits). A
learned model takes one kind (``solvers.gcn``), and a frame received from a camera keeps the
kind its message declared (:attr:`gcn_match_ros.windowing.Frame.binary`).
"""
from __future__ import annotations

from typing import Tuple

import numba
import numpy as np

__all__ = ["NORMALIZATIONS", "normalize_descriptors", "cosine_distance", "cosine_distance32", "descriptor_kind", "describe_descriptor_kind"]

NORMALIZATIONS = ("l2", "rootsift")


def normalize_descriptors(desc: np.ndarray, normalization: str = "l2") -> np.ndarray:
    """Row-normalise descriptors so that dot products are cosines.

    ``"l2"``: unit rows; ``"rootsift"`` (Hellinger): L1-normalise the absolute values, square
    root, then unit rows.

    Shapes: desc (N, D) -> (N, D) float32 with unit rows (zero rows stay zero).

    Raises:
        ValueError: an unknown normalization.
    """
    if normalization not in NORMALIZATIONS:
        raise ValueError(f"normalization must be one of {NORMALIZATIONS}, got {normalization!r}")
    d = np.asarray(desc, dtype=np.float32)
    if normalization == "rootsift":
        d = np.abs(d)
        d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.maximum(norm, 1e-12)


def cosine_distance(cos):
    """Euclidean distance between unit vectors from their cosine, sqrt(2 - 2 cos): the quantity
    Lowe's ratio is defined on. Shapes: any array (or scalar) -> the same."""
    return np.sqrt(np.maximum(2.0 - 2.0 * cos, 0.0))


@numba.njit(cache=True, nogil=True, inline="always")
def cosine_distance32(cos):
    """:func:`cosine_distance` of one float32 in compiled code, in float32 as numpy computes it
    on float32 arrays (the same bits)."""
    two = np.float32(2.0)
    return np.sqrt(max(two - two * cos, np.float32(0.0)))


def descriptor_kind(descriptors: np.ndarray) -> Tuple[int, bool]:
    """(dimension, binary) of an (N, D) descriptor array; binary = every entry 0 or 1 (the
    problem format's unpacked bits, e.g. ORB), real-valued otherwise (SIFT, learned
    descriptors). An empty array counts as real-valued."""
    d = np.asarray(descriptors)
    binary = bool(d.size) and bool(np.all((d == 0) | (d == 1)))
    return int(d.shape[1]) if d.ndim == 2 else 0, binary


def describe_descriptor_kind(kind: Tuple[int, bool]) -> str:
    """Words for a :func:`descriptor_kind`: ``'256-bit binary'``, ``'128-D real-valued'``."""
    return f"{kind[0]}-bit binary" if kind[1] else f"{kind[0]}-D real-valued"
