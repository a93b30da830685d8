"""Tests of gcn_match_ros.prefetch: a hint that compiles for any 2-D array and changes nothing."""
import numba
import numpy as np
import pytest

from gcn_match_ros.prefetch import prefetch_row


@numba.njit
def _row_sums(array, ahead):
    """Each row's sum, the rows ``ahead`` asked for first (0: none)."""
    out = np.zeros(array.shape[0])
    for i in range(array.shape[0]):
        if ahead and i + ahead < array.shape[0]:
            prefetch_row(array, i + ahead)
        for j in range(array.shape[1]):
            out[i] += array[i, j]
    return out


@pytest.mark.parametrize("array", [
    np.random.default_rng(0).random((300, 500)).astype(np.float32),           # C order, a block's size
    np.asfortranarray(np.random.default_rng(1).random((40, 30))),              # F order
    np.random.default_rng(2).integers(0, 9, (50, 64))[:, ::3],                 # a strided view
    np.zeros((1, 0), np.int8),                                                  # rows of no bytes
], ids=["c-order", "f-order", "strided", "empty-rows"])
def test_prefetching_rows_changes_no_result(array):
    """A compiled loop that asks for rows ahead computes what it computes without: the hint
    compiles for every layout and dtype and reads nothing itself."""
    np.testing.assert_array_equal(_row_sums(array, 2), _row_sums(array, 0))


def test_only_two_dimensional_arrays_take_it():
    @numba.njit
    def one_dimensional(a):
        prefetch_row(a, 0)

    with pytest.raises(numba.core.errors.TypingError):
        one_dimensional(np.zeros(3))


def test_the_hint_is_compiled_in():
    """The loop's code holds the prefetch: in its LLVM IR, and on x86-64 as instructions."""
    import platform

    array = np.zeros((4, 32), np.float32)
    _row_sums(array, 1)
    signature = _row_sums.signatures[0]
    assert "llvm.prefetch" in _row_sums.inspect_llvm(signature)
    if platform.machine() == "x86_64":
        asm = _row_sums.inspect_asm(signature)
        assert any(line.strip().startswith("prefetch") for line in asm.splitlines())
