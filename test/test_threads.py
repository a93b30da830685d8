"""Tests of gcn_match_ros.threads: numpy's BLAS on one thread, torch's pool untouched."""
import numpy as np
import torch
from threadpoolctl import threadpool_info, threadpool_limits

from gcn_match_ros.threads import single_blas_thread


def test_single_blas_thread_limits_numpys_blas_and_leaves_torch_alone():
    torch_threads = torch.get_num_threads()
    original = threadpool_limits(limits=None)  # restores whatever this process had afterwards
    try:
        single_blas_thread()
        blas = [i for i in threadpool_info() if i["user_api"] == "blas"]
        assert blas and all(i["num_threads"] == 1 for i in blas)
        a = np.random.default_rng(0).normal(size=(64, 64))
        np.testing.assert_allclose(a @ np.linalg.inv(a), np.eye(64), atol=1e-8)  # still numpy's BLAS
        assert torch.get_num_threads() == torch_threads
    finally:
        original.restore_original_limits()
