"""Tests of gcn_match_ros.buckets: every bucket sorted, stably, with its carried values."""
import numpy as np

from gcn_match_ros.buckets import sort_buckets


def test_every_bucket_is_sorted_stably_with_what_it_carries():
    rng = np.random.default_rng(0)
    sizes = np.array([0, 1, 5, 0, 30, 2, 17])
    start = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    keys = rng.integers(0, 6, start[-1]).astype(np.int64)  # many equal keys
    carried = np.arange(start[-1], dtype=np.int64)          # the original positions
    bucket = np.repeat(np.arange(sizes.size), sizes)
    want = np.lexsort((carried, keys, bucket))               # by bucket, key, then original order
    sort_buckets(start, keys, carried)
    np.testing.assert_array_equal(carried, want)
    np.testing.assert_array_equal(keys, keys[np.lexsort((keys, bucket))])
    flags = np.array([True, False, False, False])            # any carried dtype
    sort_buckets(np.array([0, 4]), np.array([3, 1, 2, 0]), flags)
    np.testing.assert_array_equal(flags, [False, False, False, True])
