"""The pipeline's stages in order. Each is one module, ``ops/stages/<id>.py``, declaring one ``Stage``
named ``STAGE`` (``ops.engine.stage``: its config class, what it reads and writes, its checks, how it
runs). Adding a stage is that module and its id in ``STAGE_IDS``: the configuration
(``ops.config.presets.PipelineConfig``), the runner (``ops.pipeline``), the Dagster assets and the QA
checks read the declarations.

Importing this package loads no stage module, so naming the stages costs no torch import (the command
line, the report); ``STAGES``, ``BY_ID`` and ``CHECKS`` load the declarations on first use.
"""

from __future__ import annotations

import functools
from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ops.engine.checks import CheckSpec, CheckThresholds, QACheck
    from ops.engine.stage import Stage

STAGE_IDS: tuple[str, ...] = ("reference", "nerf", "dmtet", "texture", "bake", "export", "qa")


@functools.cache
def declared() -> tuple[Stage, ...]:
    """The declarations in pipeline order (imports every stage module)."""
    stages = tuple(import_module(f"{__name__}.{stage_id}").STAGE for stage_id in STAGE_IDS)
    for stage_id, stage in zip(STAGE_IDS, stages, strict=True):
        if stage.id != stage_id:
            raise ImportError(f"ops/stages/{stage_id}.py declares a stage with id {stage.id!r}: a stage's id is "
                              "its module name (its config key, store folder and Dagster asset)")
    return stages


def __getattr__(name: str) -> Any:  # the declarations, loaded when first asked for (PEP 562)
    if name == "STAGES":
        return declared()
    if name == "BY_ID":
        return {s.id: s for s in declared()}
    if name == "CHECKS":  # the checks each stage's output gets; the Dagster assets declare exactly these
        return {s.id: s.checks for s in declared()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


STAGES: tuple[Stage, ...]
BY_ID: dict[str, Stage]
CHECKS: dict[str, tuple[CheckSpec, ...]]


def stage_checks(stage: str, metrics: dict[str, Any], thresholds: CheckThresholds) -> list[QACheck]:
    """A producing stage's checks from its manifest metrics (none for a stage that judges itself, ``qa``)."""
    judge = next(s for s in declared() if s.id == stage).judge
    return judge(metrics, thresholds) if judge is not None else []
