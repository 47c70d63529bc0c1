"""Fixtures shared by every test folder."""

from __future__ import annotations

from pathlib import Path

import pytest

from semmap.datasets import find_data_root


@pytest.fixture(scope="session")
def data_root() -> Path:
    """The shared real-data folder ($SEMMAP_DATA or <project>/../shared/data); skips where it is absent."""
    root = find_data_root()
    if root is None:
        pytest.skip("shared real data absent: set SEMMAP_DATA or provide <project root>/../shared/data")
    return root
