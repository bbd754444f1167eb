"""What every Triton kernel module here shares: the guarded import, where kernels can run, and the
choice between a kernel and the eager PyTorch code (``choose``).

Triton reads ``TRITON_INTERPRET`` when it is first imported (its own library functions are
``@triton.jit`` too): so this module does not import it; the kernel modules (``hashgrid_triton``,
``mlp_triton``) do, through ``load_triton``, and they are imported lazily by the code that chooses
them, after the CPU tests have set ``TRITON_INTERPRET=1``.

The choice (``auto`` | ``triton`` | ``eager``) is a field of ``morpheus_core.runtime.execution.ExecutionConfig``,
the process-wide execution settings, not of a stage's config: a kernel changes results only by
float rounding, so it must not change the fingerprints of existing stores.
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
from collections.abc import Callable
from types import ModuleType
from typing import Any

import torch


def load_triton() -> tuple[Any, Any, Any]:
    """(triton, triton.language, triton.jit) for a kernel module; (None, None, a no-op decorator)
    where Triton is not installed, so the module still imports and ``triton_available`` is False."""
    try:
        import triton
        import triton.language as tl
    except ImportError:
        return None, None, _no_jit
    return triton, tl, triton.jit


def _no_jit(fn: Any = None, **_options: Any) -> Any:
    """``triton.jit``'s stand-in, bare (``@jit``) or with options (``@jit(do_not_specialize=...)``)."""
    return fn if fn is not None else (lambda f: f)


def interpreting() -> bool:
    """Whether Triton runs its CPU interpreter (``TRITON_INTERPRET=1``) instead of compiling."""
    return os.environ.get("TRITON_INTERPRET", "0") == "1"


def triton_available() -> bool:
    """Triton imports and can run here: a CUDA device is present, or the interpreter is on."""
    return importlib.util.find_spec("triton") is not None and (torch.cuda.is_available() or interpreting())


def device_guard(x: torch.Tensor) -> Any:
    """The CUDA device context of ``x`` (kernels launch on the current device), a no-op on the CPU."""
    return torch.cuda.device(x.device) if x.device.type == "cuda" else contextlib.nullcontext()


def choose(choice: str, key: str, device: torch.device, supported: Callable[[], bool],
           load: Callable[[], ModuleType], what: str) -> ModuleType | None:
    """The kernel module ``load()`` when ``choice`` (the setting ``key`` of ``ExecutionConfig``,
    validated there) asks for it and it can run on ``device``, else None (the caller's eager code).

    ``auto``: the kernels on CUDA; the CPU never imports them (nor Triton), so its path stays the
    eager code. ``triton``: insist, an error where they cannot run (a CPU without
    ``TRITON_INTERPRET=1``). ``eager``: the tensor code everywhere. Inputs the kernels do not take
    (``supported()`` false: float64 for gradcheck, an unsupported width) run eagerly under any choice.
    """
    if choice == "eager" or (choice == "auto" and device.type != "cuda"):
        return None
    if not supported():
        return None
    if triton_available() and (device.type == "cuda" or interpreting()):
        return load()
    if choice == "triton":
        reason = "triton is not installed" if importlib.util.find_spec("triton") is None else (
            f"Triton needs a CUDA device (or TRITON_INTERPRET=1 for its CPU interpreter), got {device}")
        raise RuntimeError(f"{key}=triton but the Triton {what} kernels cannot run here: {reason}; "
                           f"set {key}=auto or eager")
    return None
