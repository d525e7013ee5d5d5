"""keep_freed_host_memory: freed scratch is reused, not mapped afresh (run in a child process, whose
allocator settings the test may change)."""

import subprocess
import sys

import pytest

CHILD = """
import resource, sys
import numpy as np
from nanogs_warp.device import keep_freed_host_memory

def faults_of_a_fresh_64_mb_block():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        block = np.empty(64 << 20, dtype=np.uint8)
        block.fill(1)  # touch every page
        del block
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

faults_of_a_fresh_64_mb_block()
default = faults_of_a_fresh_64_mb_block()
if not keep_freed_host_memory():
    print("unsupported")
    sys.exit(0)
faults_of_a_fresh_64_mb_block()
kept = faults_of_a_fresh_64_mb_block()
print(default, kept)
"""


def test_freed_blocks_are_reused():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, check=True).stdout.split()
    if out == ["unsupported"]:
        pytest.skip("not glibc")
    default, kept = map(int, out)
    assert default >= 150  # 5 x 64 MB mapped afresh by default: 81,920 pages of 4 KiB, or 160 huge pages
    assert kept < default // 10
