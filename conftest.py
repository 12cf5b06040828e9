"""Test-wide settings (tests and the package's docstring examples)."""
import pytest
import torch


@pytest.fixture(autouse=True)
def torch_single_thread():
    """Runs every test with one intra-op thread.

    The networks here are tiny: on a 2-core machine, OpenMP's 2-thread kernels only wait on each other (a small
    ``nn.Linear`` call takes milliseconds instead of microseconds). Closing a ``SerialEnv``/``ParallelEnv`` also
    resets torch's thread count, so it is set again for each test.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
