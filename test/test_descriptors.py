"""Tests of gcn_match_ros.descriptors: row normalisation (L2, RootSIFT) and the descriptor kind."""
import numba
import numpy as np
import pytest

from gcn_match_ros.descriptors import (cosine_distance, cosine_distance32, describe_descriptor_kind, descriptor_kind,
                                       normalize_descriptors)


def _random_descriptors(seed=0, n=6, dim=16):
    d = np.random.default_rng(seed).normal(size=(n, dim))
    d[2] = 0.0  # a zero row must stay zero, not become NaN
    return d


def test_l2_rows_are_unit_and_zero_rows_stay_zero():
    d = _random_descriptors()
    out = normalize_descriptors(d, "l2")
    assert out.dtype == np.float32 and out.shape == d.shape
    nonzero = np.arange(len(d)) != 2
    np.testing.assert_allclose(out[nonzero], d[nonzero] / np.linalg.norm(d[nonzero], axis=1, keepdims=True),
                               rtol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(out[nonzero], axis=1), 1.0, rtol=1e-6)
    assert np.all(out[2] == 0)
    np.testing.assert_array_equal(normalize_descriptors(d), out)  # l2 is the default


def test_rootsift_is_the_hellinger_kernel():
    d = _random_descriptors(1)
    out = normalize_descriptors(d, "rootsift")
    assert out.dtype == np.float32 and np.all(out >= 0) and np.all(out[2] == 0)
    p = np.abs(d) / np.maximum(np.abs(d).sum(axis=1, keepdims=True), 1e-12)  # L1-normalised histograms
    nonzero = np.arange(len(d)) != 2
    np.testing.assert_allclose(out[nonzero], np.sqrt(p[nonzero]), rtol=1e-6)
    # dot products are the Bhattacharyya coefficients sum_k sqrt(p_k q_k)
    i, j = 0, 4
    assert float(out[i] @ out[j]) == pytest.approx(np.sum(np.sqrt(p[i] * p[j])), rel=1e-6)


def test_descriptor_kind_and_its_words():
    rng = np.random.default_rng(2)
    assert descriptor_kind(rng.normal(size=(5, 128)).astype(np.float32)) == (128, False)
    assert descriptor_kind(rng.integers(0, 2, (5, 256)).astype(np.float32)) == (256, True)
    assert descriptor_kind(np.array([[0.0, 1.0, 0.5]])) == (3, False)  # one non-bit value: real-valued
    assert descriptor_kind(np.zeros((0, 64), np.float32)) == (64, False)  # empty: real-valued
    assert describe_descriptor_kind((256, True)) == "256-bit binary"
    assert describe_descriptor_kind((128, False)) == "128-D real-valued"


@numba.njit
def _compiled_cosine_distances(cos):
    out = np.empty_like(cos)
    for m in range(cos.shape[0]):
        out[m] = cosine_distance32(cos[m])
    return out


def test_compiled_cosine_distance_is_numpys_float32_bit_for_bit():
    rng = np.random.default_rng(3)
    cos = np.r_[rng.uniform(-1.0, 1.0, 100_000), 1.0, 1.0 + 1e-6, -1.0, 0.0, 0.999999].astype(np.float32)
    got = _compiled_cosine_distances(cos)
    assert got.dtype == np.float32 and got[-3] == 2.0 and got[-4] == 0.0  # cos above 1: clipped to 0
    np.testing.assert_array_equal(got, cosine_distance(cos))
