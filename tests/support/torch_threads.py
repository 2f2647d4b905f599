"""A fixture for tests that render images of a few hundred pixels with torch.

One intra-op thread is faster than two there, and far faster when other jobs share the cores: a 48 x 36 render
took 17 ms with one thread against 90 ms (median of 10) with two while another job ran on the 2 cores.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread() -> Iterator[None]:
    """Run the module's tests with one torch thread, then restore the count."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
