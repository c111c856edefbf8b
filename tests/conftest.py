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


requires_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (CI has none)")
