"""How the method's kernels run, as one process-wide setting: ``ExecutionConfig``.

These choices (fused Triton kernels or the eager tensor code, ``torch.compile`` or not) change
results only by float rounding, so they are not part of any stage's config: a run applies its
``ExecutionConfig`` once at start-up (``apply_execution``, or ``executing`` for a scope) and the
kernels read ``current_execution()``, a module-level value, never the environment.

The environment variables ``MORPHEUS_HASHGRID``, ``MORPHEUS_FIELD_MLP`` and ``MORPHEUS_COMPILE``
are aliases that give the defaults; ``ExecutionConfig.from_env`` is the only reader. A process
that never applies one (a benchmark, a test calling the method directly) gets those defaults.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Literal, get_args

KernelChoice = Literal["auto", "triton", "eager"]
KERNEL_CHOICES: tuple[str, ...] = get_args(KernelChoice)

# Field name → its environment alias (documented in docs/performance.md, "Execution settings").
ENV_ALIASES = {"hashgrid": "MORPHEUS_HASHGRID", "field_mlp": "MORPHEUS_FIELD_MLP", "compile": "MORPHEUS_COMPILE"}
_TRUE, _FALSE = ("1", "true", "on", "yes"), ("0", "false", "off", "no")


@dataclass(frozen=True)
class ExecutionConfig:
    """Which kernels run the method; never part of a stage's fingerprint (results differ by rounding only)."""

    hashgrid: KernelChoice = "auto"
    """Hash-grid encode: ``triton`` (fused kernels; an error where they cannot run), ``eager`` (tensor code);
    ``auto``: Triton on CUDA, eager elsewhere. Alias ``MORPHEUS_HASHGRID``."""
    field_mlp: KernelChoice = "auto"
    """NeRF density/albedo heads: ``triton`` (fused kernels), ``eager`` (the ``nn.Sequential`` modules);
    ``auto``: Triton on CUDA, eager elsewhere. Alias ``MORPHEUS_FIELD_MLP``."""
    compile: bool = True
    """``torch.compile`` the hot tensor code on CUDA (the CPU never compiles). Alias ``MORPHEUS_COMPILE`` (0/1)."""

    def __post_init__(self) -> None:
        for name in ("hashgrid", "field_mlp"):
            value = getattr(self, name)
            if value not in KERNEL_CHOICES:
                raise ValueError(f"execution.{name} must be one of {', '.join(KERNEL_CHOICES)}; got {value!r}")
        if not isinstance(self.compile, bool):
            raise ValueError(f"execution.compile must be true or false; got {self.compile!r}")

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> ExecutionConfig:
        """The defaults from the environment aliases (``ENV_ALIASES``; unset or empty: the field's
        default). A bad value raises ``ValueError`` naming the variable and the key."""
        env = os.environ if env is None else env
        values: dict[str, str | bool] = {}
        for name, var in ENV_ALIASES.items():
            text = env.get(var, "").strip().lower()
            if not text:
                continue
            if name == "compile":
                if text not in _TRUE + _FALSE:
                    raise ValueError(f"{var} (execution.compile) must be 0 or 1; got {env[var]!r}")
                values[name] = text in _TRUE
            elif text not in KERNEL_CHOICES:
                raise ValueError(f"{var} (execution.{name}) must be one of {', '.join(KERNEL_CHOICES)}; "
                                 f"got {env[var]!r}")
            else:
                values[name] = text
        return cls(**values)  # type: ignore[arg-type]


# None until first read or applied: a process that never applies a config gets the environment's.
_current: ExecutionConfig | None = None


def current_execution() -> ExecutionConfig:
    """The process-wide execution settings the kernels follow."""
    global _current
    if _current is None:
        _current = ExecutionConfig.from_env()
    return _current


def apply_execution(cfg: ExecutionConfig) -> ExecutionConfig:
    """Make ``cfg`` the process-wide execution settings; returns the ones it replaces."""
    global _current
    previous = current_execution()
    _current = cfg
    return previous


@contextmanager
def executing(cfg: ExecutionConfig) -> Iterator[ExecutionConfig]:
    """``cfg`` applied for the ``with`` block, the previous settings back afterwards (a run in a
    process that runs several, such as a test session or Dagster's in-process executor)."""
    previous = apply_execution(cfg)
    try:
        yield cfg
    finally:
        apply_execution(previous)
