"""Shared test set-up: Warp initialised once (its kernel cache is shared by every test), and the
devices every kernel test runs on: the CPU always, the first GPU when there is one."""

import sys
from pathlib import Path

import pytest
import warp as wp

from nanogs_warp.device import init_warp

sys.path.insert(0, str(Path(__file__).parent))  # tests import reference.py and scene_factory.py

init_warp()
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", DEVICES)


@pytest.fixture
def rng(request):
    """A fresh generator per test, seeded from the test's name so failures reproduce."""
    import zlib

    import numpy as np

    return np.random.default_rng(zlib.crc32(request.node.nodeid.encode()))
