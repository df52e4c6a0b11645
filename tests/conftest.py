"""Shared fixtures."""
import pytest
import torch


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
