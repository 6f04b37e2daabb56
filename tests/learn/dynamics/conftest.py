import pytest
import torch


@pytest.fixture(autouse=True)
def one_torch_thread():
    """One torch thread: the tests' tensors are tiny, and on a shared machine OpenMP threads
    spinning for a core they do not get slow them down many times over."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
