"""Shared fixtures: device, dtype and backend, and the one-thread switch of many-small-op modules."""
import pytest
import torch

import difftex
from difftex import _native as native

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]
# The implementations difftex.backend chooses among (the "auto" default is "native" where the kernel serves).
BACKENDS = ("native", "grid_sample", "reference")


def use_backend(name: str):
    """``difftex.backend(name)`` as a context manager; skips the test where the native kernel is not built."""
    if name == "native" and native.load() is None:
        pytest.skip("native kernel not built here (DIFFTEX_NATIVE=0, or no compiler)")
    return difftex.backend(name)


@pytest.fixture(params=DEVICES)
def device(request) -> str:
    return request.param


@pytest.fixture(params=DTYPES, ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param


@pytest.fixture(params=BACKENDS)
def backend(request) -> str:
    """Runs the test under each backend (``difftex.backend``), restoring the previous choice afterwards."""
    with use_backend(request.param):
        yield request.param


@pytest.fixture(scope="module")
def one_thread():
    """Run a module on one intra-op thread, restoring the setting afterwards.

    Modules of many small ops use it: on a shared 2-core machine every
    intra-op thread hand-off can stall for milliseconds, so one thread is
    both faster and steadier.
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
