"""Shared fixtures."""
import pytest


@pytest.fixture
def one_torch_thread():
    """2 shared CPU cores: torch intra-op threads only oversubscribe."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
