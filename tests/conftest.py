"""Shared fixtures: the test device, and tiny random models of the priors' real architectures
(saved once per session). ``MORPHEUS_TEST_DEVICE=cuda pytest`` runs the device-aware tests on a GPU."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from morpheus_core.priors.image2d import Image2DPrior, Image2DSettings
from morpheus_core.priors.registry import ModelRegistry
from morpheus_core.priors.zero123 import Zero123Prior
from tests.helpers import RES_2D
from tests.seeds import TEST_SEED_ENV, seed_session
from tests.tiny_models import write_all


def pytest_configure(config: pytest.Config) -> None:
    seed_session()  # before xdist starts its workers: they inherit the seed through the environment
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        # Each worker gets its share of the cores, and so do the processes its tests start: torch's
        # default of one thread per core in every worker oversubscribed 2 cores (docs/testing.md).
        threads = max(1, (os.cpu_count() or 1) // workers)
        torch.set_num_threads(threads)
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(threads)


def pytest_report_header(config: pytest.Config) -> str:
    return f"fresh test seeds from {TEST_SEED_ENV}={os.environ[TEST_SEED_ENV]} (set it to draw the same ones again)"


@pytest.fixture(autouse=True)
def _subnormals_back() -> object:
    # ``run_loop`` flushes subnormals process-wide (a CPU speed fix); a later test in the same process
    # that draws IEEE floats (hypothesis refuses to without subnormals) needs them back.
    yield
    torch.set_flush_denormal(False)


@pytest.fixture
def device() -> torch.device:
    name = os.environ.get("MORPHEUS_TEST_DEVICE", "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        pytest.skip(f"MORPHEUS_TEST_DEVICE={name} but CUDA is not available")
    return torch.device(name)


@pytest.fixture(scope="session")
def models_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_all(tmp_path_factory.mktemp("models"))


@pytest.fixture(scope="session")
def registry(models_root: Path) -> ModelRegistry:
    return ModelRegistry(root=models_root)


@pytest.fixture(scope="session")
def zero123(registry: ModelRegistry) -> Zero123Prior:
    """Shared: tests give their references unique object ids and never add adapters to it."""
    return Zero123Prior.from_registry(registry)


@pytest.fixture
def load_image2d(registry: ModelRegistry) -> Callable[[], Image2DPrior]:
    """A fresh 2D prior per call (LoRA tests add adapters to its UNet)."""
    return lambda: Image2DPrior.from_registry(registry, settings=Image2DSettings(resolution=RES_2D))


@pytest.fixture(scope="session")
def image2d(registry: ModelRegistry) -> Image2DPrior:
    return Image2DPrior.from_registry(registry, settings=Image2DSettings(resolution=RES_2D))
