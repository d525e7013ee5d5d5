"""Shared test set-up: Warp initialised once (its kernel cache is shared by every test), and the
devices every kernel test runs on: the CPU always, the first GPU when there is one."""

import signal
import sys
from pathlib import Path

import pytest
import warp as wp

from nanogs_warp.device import init_warp

sys.path.insert(0, str(Path(__file__).parent))  # tests import reference.py and scene_factory.py

init_warp()

# A suite started in the background by a non-interactive shell (``cmd &``) inherits SIGINT ignored, and
# so would every command the tests start: the tests of Ctrl-C would see nothing happen. Python's own
# handler, as in a terminal (the commands they start then get the default disposition).
if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

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
