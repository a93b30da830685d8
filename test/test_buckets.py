"""Tests of gcn_match_ros.buckets: every bucket sorted, stably, with its carried values; the
counting sort's order."""
import numpy as np

from gcn_match_ros.buckets import bucket_order, bucket_starts, sort_buckets


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


def test_bucket_order_is_a_stable_sort_by_key_with_the_boundaries():
    keys = np.random.default_rng(1).integers(0, 7, 200).astype(np.int64)
    keys[keys == 3] = 4  # an empty bucket
    start, order = bucket_order(keys, 9)  # and two empty ones at the end
    np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))
    np.testing.assert_array_equal(start, np.r_[0, np.cumsum(np.bincount(keys, minlength=9))])
    np.testing.assert_array_equal(bucket_starts(keys, 9), start)
    start, order = bucket_order(np.zeros(0, np.int64), 3)
    assert order.size == 0 and np.all(start == 0)
