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


def pytest_runtest_setup(item: pytest.Item) -> None:
    """`needs_data` / `needs_model` tests skip, with the reason, where the data or the model is absent."""
    if item.get_closest_marker("needs_data") and find_data_root() is None:
        pytest.skip("shared real data absent: set SEMMAP_DATA or provide <project root>/../shared/data")
    if item.get_closest_marker("needs_model"):
        from services.detector.model_store import default_model_path

        if not default_model_path().is_file():
            pytest.skip("detector model absent: run `semmap models fetch` (./dev.sh does)")
