import pytest
import torch


@pytest.fixture
def torch_single_thread():
    """Runs a test with one intra-op thread.

    On a 2-core machine shared with other processes, OpenMP's 2-thread kernels wait on each other: a tiny
    ``nn.Linear`` call takes milliseconds instead of microseconds.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
