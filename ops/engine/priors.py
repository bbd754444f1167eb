"""Which priors guide a stage, bound per step: the real ones from local weights, or the proxy.

A stage asks for roles (``"3d"``, ``"2d"``) and which of them run VSD; the suite binds each role
to a prior, its VSD counterpart and this step's condition, so the stage code is the same for the
weight-free proxy and the real models.

- ``proxy`` (weight-free): both roles are pulled towards renders of the photo's inflated
  silhouette (``morpheus_core.priors.proxy.shape``); VSD's counterpart is the current render (see
  ``CurrentRenderCounterpart``). Used whenever the weights are missing, and said so loudly.
- ``real``: Zero123 for ``3d``; SD1.5 + canny ControlNet + IP-Adapter for ``2d``; one LoRA per
  object for every VSD role. Loaded once per process and device (``ModelCache``).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from morpheus_core.cameras import Cameras
from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.hybrid import PriorBinding
from morpheus_core.priors.lora import LoraSettings, ObjectLoras
from morpheus_core.priors.proxy.denoiser_error import DenoiserError
from morpheus_core.priors.proxy.prior import Corruption, CurrentRenderCounterpart, ProxyPrior
from morpheus_core.priors.proxy.shape import InflatedProxy, InflationConfig
from morpheus_core.priors.registry import PRIOR_MODELS, ModelRegistry
from morpheus_core.priors.runtime import PriorRuntime
from morpheus_core.runtime.cuda_graphs import release_graphs
from ops.engine.target import read_rgba

log = logging.getLogger("morpheus3d")

PriorKind = Literal["auto", "proxy", "real"]
WEIGHT_FREE = "proxy (weight-free)"


@dataclass(frozen=True)
class PriorsConfig:
    """Which diffusion priors guide the fitting stages, where their weights live and how they run."""

    kind: PriorKind = "auto"
    """``real`` (Zero123, SD1.5; needs the weights), ``proxy`` (weight-free); ``auto``: real if all weights exist."""
    models_root: str | None = None
    """Folder holding the prior weights; None: ``$MORPHEUS_MODELS``, else ``~/.cache/morpheus3d/models``."""
    dtype: Literal["auto", "float32", "float16", "bfloat16"] = "auto"
    """Precision of the frozen prior networks; ``auto``: float16 on CUDA (as the paper), float32 elsewhere."""
    vae_dtype: Literal["auto", "float32", "float16", "bfloat16"] = "auto"
    """Precision of the VAE that encodes every step's renders; ``auto``: float32 under float16 priors (the SD
    VAE overflows in float16), else ``dtype``. bfloat16 keeps float32's range."""
    accel: Literal["auto", "eager", "cudagraph", "compile"] = "auto"
    """Frozen forwards: eager, cudagraph or compile; auto: CUDA graphs on CUDA (68 → 20 ms a Zero123 step, H200)."""
    image2d_resolution: int = 512
    """Side (px) renders are resized to for the 2D prior (SD1.5 + ControlNet); 512 is SD1.5's native size."""
    lora: LoraSettings = field(default_factory=LoraSettings)
    """The per-object LoRA that VSD trains on each prior as its counterpart ε_φ."""
    proxy_grid: int = 48
    """DMTet grid resolution (cells per side, 4–1024) that meshes the weight-free proxy's inflated silhouette."""
    proxy_thickness: float = 1.0
    """Proxy depth relative to a round profile: 1.0 inflates a disk silhouette to a sphere, 0.5 to a half-deep lens."""

    def __post_init__(self) -> None:
        if self.kind not in ("auto", "proxy", "real"):
            raise ValueError(f"priors.kind must be auto, proxy or real, got {self.kind!r}")

    def registry(self) -> ModelRegistry:
        return ModelRegistry(root=Path(self.models_root)) if self.models_root else ModelRegistry()

    def resolve(self, roles: tuple[str, ...]) -> str:
        """``proxy`` or ``real`` for these roles; ``real`` asked for without weights raises."""
        if self.kind == "proxy":
            return "proxy"
        reg = self.registry()
        ready = all(reg.prior_ready(role) for role in roles)
        if self.kind == "real" and not ready:
            missing = [n for role in roles for n in PRIOR_MODELS[role] if not reg.status(n).present]
            reg.require(missing[0])  # raises ModelMissingError naming the folder and its files
        return "real" if ready else "proxy"

    def runtime(self, device: torch.device) -> PriorRuntime:
        accel = self.accel
        if accel == "auto":
            accel = "cudagraph" if torch.device(device).type == "cuda" else "eager"
        rt = PriorRuntime.for_device(device, accel)
        dtype = rt.dtype if self.dtype == "auto" else getattr(torch, self.dtype)
        vae = None if self.vae_dtype == "auto" else getattr(torch, self.vae_dtype)
        return PriorRuntime(rt.device, dtype, vae, channels_last=rt.channels_last, accel=rt.accel)


@dataclass(frozen=True)
class ProxyCondition:
    target: Tensor
    current: Tensor


class PriorSuite(ABC):
    """Binds roles to priors for one object; ``description`` goes to logs and manifests."""

    description: str
    weight_free: bool

    @abstractmethod
    def bindings(self, cameras: Cameras, renders: Tensor) -> dict[str, PriorBinding]:
        """Each role's prior, VSD counterpart and condition for this step's cameras and renders."""

    # The no-op defaults below are right for suites without trainable state (the proxy).
    def after_step(self, ok: Tensor | bool) -> None:  # noqa: B027
        """Step the VSD counterparts after a good step; drop their gradients after a bad one."""

    def state(self) -> dict[str, Any]:
        return {}

    def load_state(self, state: Mapping[str, Any]) -> None:  # noqa: B027
        """Restore what ``state`` returned."""

    def close(self) -> None:  # noqa: B027
        """Release per-object state (adapters, cached references)."""


class ProxySuite(PriorSuite):
    """Render-target priors: each role is pulled towards ``target_images(cameras, h, w)`` (B×3×H×W),
    through that role's corruption if it has one, and erring like a real denoiser where the role has
    an error model. The weight-free default targets the photo's inflated silhouette (noise-free); the
    quality benchmark's oracle targets a known object, low-passed for ``3d`` and colour-shifted in its
    low band for ``2d`` (DESIGN.md §3), by default with ``DenoiserError``s (``benchmarks/oracle.py``)."""

    weight_free = True

    def __init__(self, target_images: Callable[[Cameras, int, int], Tensor], roles: tuple[str, ...],
                 vsd_roles: tuple[str, ...], description: str,
                 corruptions: Mapping[str, Corruption] | None = None,
                 errors: Mapping[str, DenoiserError] | None = None) -> None:
        self.target_images = target_images
        self.roles = roles
        self.vsd_roles = vsd_roles
        self.description = description
        schedule = NoiseSchedule()
        corruptions, errors = corruptions or {}, errors or {}
        self.priors = {role: ProxyPrior(lambda c: c.target, schedule, corruptions.get(role), errors.get(role),
                                        lambda c: c.current) for role in roles}
        self.counterparts = {role: CurrentRenderCounterpart(lambda c: c.current, schedule, errors.get(role))
                             for role in roles}

    def bindings(self, cameras: Cameras, renders: Tensor) -> dict[str, PriorBinding]:
        h, w = renders.shape[-2:]
        target = self.target_images(cameras, h, w).to(device=renders.device, dtype=renders.dtype)
        cond = ProxyCondition(target, renders.detach())
        return {role: PriorBinding(self.priors[role], self.counterparts[role] if role in self.vsd_roles else None, cond)
                for role in self.roles}


class ModelCache:
    """Loaded real priors, kept for the process: loading is slow and the weights are frozen. Each
    model's per-object LoRA adapters live in one ``ObjectLoras`` per (model, settings), so objects
    optimised together share it and one row-batched forward serves them all."""

    _models: dict[tuple[str, str, str], Any] = {}  # noqa: RUF012 — a process-wide cache by design
    _loras: dict[tuple[int, LoraSettings], ObjectLoras] = {}  # noqa: RUF012

    @classmethod
    def loras(cls, model: Any, settings: LoraSettings) -> ObjectLoras:
        key = (id(model), settings)
        if key not in cls._loras:
            cls._loras[key] = ObjectLoras(model, settings)
        return cls._loras[key]

    @classmethod
    def get(cls, role: str, cfg: PriorsConfig, runtime: PriorRuntime) -> Any:
        key = (role, str(cfg.registry().resolved_root()[0]), repr(runtime))
        if key not in cls._models:
            from morpheus_core.priors.image2d import Image2DPrior, Image2DSettings
            from morpheus_core.priors.zero123 import Zero123Prior

            log.info("loading the %s prior (%s) on %s", role, ", ".join(PRIOR_MODELS[role]), runtime.device)
            if role == "3d":
                cls._models[key] = Zero123Prior.from_registry(cfg.registry(), runtime)
            else:
                settings = Image2DSettings(resolution=cfg.image2d_resolution)
                cls._models[key] = Image2DPrior.from_registry(cfg.registry(), runtime, settings)
        return cls._models[key]


class RealSuite(PriorSuite):
    weight_free = False

    def __init__(self, cfg: PriorsConfig, device: torch.device, object_id: str, reference_rgba: Tensor,
                 roles: tuple[str, ...], vsd_roles: tuple[str, ...], models: Mapping[str, Any] | None = None) -> None:
        """``models``: priors per role already built (benchmarks with random full-size networks);
        by default they are loaded from the weights folder."""
        self.object_id = object_id
        if models is None:
            runtime = cfg.runtime(device)
            models = {role: ModelCache.get(role, cfg, runtime) for role in roles}
        self.models = {role: models[role] for role in roles}
        for model in self.models.values():
            model.set_reference(object_id, reference_rgba)
        settings = cfg.lora
        self.loras: dict[str, ObjectLoras] = {}
        for role in vsd_roles:
            loras = ModelCache.loras(self.models[role], settings)
            loras.add(object_id)
            self.loras[role] = loras
        names = {"3d": "Zero123", "2d": "SD1.5 + canny ControlNet + IP-Adapter"}
        self.description = " + ".join(f"{role}: {names[role]}" + (" (VSD LoRA)" if role in self.loras else "")
                                      for role in roles)

    def bindings(self, cameras: Cameras, renders: Tensor) -> dict[str, PriorBinding]:
        ids = [self.object_id] * renders.shape[0]
        out = {}
        for role, model in self.models.items():
            if role == "3d":
                cond = model.condition(ids, cameras.elevation, cameras.azimuth, cameras.distance)
            else:
                cond = model.condition(ids, renders.detach())
            out[role] = PriorBinding(model, self.loras.get(role), cond)
        return out

    def after_step(self, ok: Tensor | bool) -> None:
        for loras in self.loras.values():
            loras.step([self.object_id], ok)  # also skips an adapter whose own gradients are not finite

    def state(self) -> dict[str, Any]:
        return {role: {"adapter": loras.state_dict(self.object_id),
                       "optimizer": loras.optimizer_state_dict(self.object_id)}
                for role, loras in self.loras.items()}

    def load_state(self, state: Mapping[str, Any]) -> None:
        for role, loras in self.loras.items():
            loras.load_state_dict(self.object_id, dict(state[role]["adapter"]))
            loras.load_optimizer_state_dict(self.object_id, state[role]["optimizer"])

    def close(self) -> None:
        """Idempotent: a stage's failed start closes its suite, and so may the caller that made it."""
        for loras in self.loras.values():
            if self.object_id in loras.object_ids:
                loras.remove(self.object_id)
        for model in self.models.values():
            model.forget(self.object_id)
        release_graphs()  # the shared priors' graphs end with the stage (morpheus_core.runtime.cuda_graphs)


def build_suite(cfg: PriorsConfig, device: torch.device, reference_dir: Path, object_id: str,
                roles: tuple[str, ...], vsd_roles: tuple[str, ...] = ()) -> PriorSuite:
    """The suite for one object and stage; logs a loud warning when it falls back to the proxy."""
    if cfg.resolve(roles) == "real":
        return RealSuite(cfg, device, object_id, read_rgba(reference_dir, 256), roles, vsd_roles)
    rgba = read_rgba(reference_dir, 256).permute(1, 2, 0).to(device)
    proxy = InflatedProxy(rgba, InflationConfig(thickness=cfg.proxy_thickness, grid_resolution=cfg.proxy_grid))
    description = (f"{WEIGHT_FREE}: renders of the photo's inflated silhouette, photo on the front and mirrored "
                   "on the back — diffusion weights are not installed (see `morpheus3d doctor`)")
    suite = ProxySuite(proxy.target_images, roles, vsd_roles, description)
    log.warning("NO DIFFUSION WEIGHTS: using the %s", suite.description)
    return suite
