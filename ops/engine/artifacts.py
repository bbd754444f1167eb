"""A stage's saved files: modules as safetensors (with the config that rebuilds them), run logs, and
the finiteness check every output passes before it is written."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from assets_store.atomic import atomic_write
from assets_store.runlog import write_runlog
from ops.engine.config_tree import from_dict, to_dict
from ops.engine.loop import LoopResult

RUNLOG_FILE = "runlog.parquet"


def save_module(path: Path, module: nn.Module, config: Any, extra: dict[str, Tensor] | None = None) -> Path:
    """A module's weights (+ ``extra`` tensors) as safetensors, with the config that rebuilds it in
    the header. safetensors is byte-for-byte reproducible (torch.save is not across processes),
    so equal weights give equal content hashes and downstream caches hold."""
    from safetensors.torch import save_file

    tensors = {f"state.{k}": v.detach().cpu().contiguous() for k, v in module.state_dict().items()}
    tensors.update({f"extra.{k}": v.detach().cpu().contiguous() for k, v in (extra or {}).items()})
    meta = {"config": json.dumps(to_dict(config), sort_keys=True)}
    return atomic_write(path, lambda tmp: save_file(tensors, str(tmp), metadata=meta))


def load_module(path: Path, cls: type, config_cls: type, device: torch.device
                ) -> tuple[nn.Module, Any, dict[str, Tensor]]:
    """Rebuild a module saved by ``save_module``; returns (module, config, extra tensors)."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    if not Path(path).is_file():
        raise FileNotFoundError(f"{path} is missing: run the stage that writes it first")
    with safe_open(str(path), framework="pt") as fh:
        meta = fh.metadata() or {}
    if "config" not in meta:
        raise ValueError(f"{path} has no config header: not written by this pipeline")
    config = from_dict(config_cls, json.loads(meta["config"]))
    tensors = load_file(str(path))
    module = cls(config)
    module.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("state.")})
    return module.to(device), config, {k[6:]: v for k, v in tensors.items() if k.startswith("extra.")}


def write_log(out_dir: Path, result: LoopResult) -> None:
    write_runlog(Path(out_dir) / RUNLOG_FILE, result.history)


def require_finite_output(name: str, tensors: dict[str, Tensor]) -> None:
    """The last line of defence: an output with NaN/Inf is never written."""
    for key, t in tensors.items():
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            raise FloatingPointError(f"{name}: {key} holds NaN/Inf; refusing to write a broken output")
