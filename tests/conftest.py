"""Shared test fixtures.

Tests that read the real data in ``../shared/data`` (relative to the project root)
take the ``shared_data`` fixture: they are skipped, with the reason, when a
checkout has no such folder (a user's clone).
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = (ROOT / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (../shared/data beside the checkout); "
                    "these tests need the PASCAL3D+ CAD models and PASCAL VOC aeroplanes")
    return SHARED_DATA


@pytest.fixture
def generator() -> torch.Generator:
    """A seeded CPU generator, so every test is deterministic."""
    return torch.Generator().manual_seed(0)


def cuda_available() -> bool:
    return torch.cuda.is_available()


#: Marks a test as needing CUDA: ``pytest -m cuda`` selects every such test (a session with a
#: GPU runs them all with ``tools/gpu_session.sh``); without a device they are skipped by
#: :func:`pytest_collection_modifyitems`.
requires_cuda = pytest.mark.cuda


def pytest_collection_modifyitems(config, items):
    """Skip the tests marked ``cuda`` when no CUDA device is present, with the reason."""
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (CI has none)")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)
