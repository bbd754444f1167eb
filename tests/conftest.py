"""Shared fixtures. ``MORPHEUS_TEST_DEVICE=cuda pytest`` runs the device-aware tests on a GPU."""

from __future__ import annotations

import os

import pytest
import torch


@pytest.fixture
def device() -> torch.device:
    name = os.environ.get("MORPHEUS_TEST_DEVICE", "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip(f"MORPHEUS_TEST_DEVICE={name} but CUDA is not available")
    return torch.device(name)
