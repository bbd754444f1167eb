"""The pipeline's stages, one module each, in order: ``STAGES`` is what the pipeline, the Dagster
assets and the QA checks read. Adding a stage: its module (a ``Stage`` with its checks), its line here and its
id in ``ops.engine.stage_ids``."""

from typing import Any

from ops.engine.checks import CheckSpec, CheckThresholds, QACheck
from ops.engine.stage import Stage
from ops.engine.stage_ids import STAGE_IDS
from ops.stages import bake, dmtet, export, nerf, qa, reference, texture

STAGES: tuple[Stage, ...] = (reference.STAGE, nerf.STAGE, dmtet.STAGE, texture.STAGE, bake.STAGE, export.STAGE,
                             qa.STAGE)
BY_ID: dict[str, Stage] = {s.id: s for s in STAGES}
if tuple(BY_ID) != STAGE_IDS:
    raise ImportError(f"ops.stages declares {tuple(BY_ID)}, ops.engine.stage_ids orders {STAGE_IDS}")
# The checks each stage's output gets, by stage id; the Dagster assets declare exactly these.
CHECKS: dict[str, tuple[CheckSpec, ...]] = {s.id: s.checks for s in STAGES}


def stage_checks(stage: str, metrics: dict[str, Any], thresholds: CheckThresholds) -> list[QACheck]:
    """A producing stage's checks from its manifest metrics (none for a stage that judges itself, ``qa``)."""
    judge = BY_ID[stage].judge
    return judge(metrics, thresholds) if judge is not None else []
