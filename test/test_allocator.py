"""Tests of gcn_match_ros.allocator: freed memory kept for reuse, measured by page faults."""
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# A window's pattern: 20 arrays of 4 MiB live at once, then all freed; five rounds. Run in a
# fresh interpreter each time, so the allocator starts from glibc's defaults.
_ROUNDS = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from gcn_match_ros.allocator import keep_freed_memory
    assert keep_freed_memory()  # glibc: the Linux wheels of ROS 2 Jazzy
def window():
    arrays = [np.ones(2**19) for _ in range(20)]  # 20 x 4 MiB, every page touched
    del arrays
window()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(4):
    window()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults_after_the_first_window(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", _ROUNDS, mode], capture_output=True, text=True, check=True,
                         cwd=REPO)
    return int(out.stdout.strip())


def test_kept_memory_is_not_faulted_in_again_window_after_window():
    default, kept = _faults_after_the_first_window("default"), _faults_after_the_first_window("keep")
    # glibc's own thresholds give about half of the 80 MiB back after every window (~10 000 pages)
    assert default > 20_000
    assert kept < default / 20
