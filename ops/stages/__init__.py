"""The pipeline's stages, one module each, in order: ``STAGES`` is what the pipeline, the Dagster
assets and the QA checks read."""

from ops.engine.stage import Stage
from ops.engine.stage_ids import STAGE_IDS
from ops.stages import bake, dmtet, export, nerf, qa, reference, texture

STAGES: tuple[Stage, ...] = (reference.STAGE, nerf.STAGE, dmtet.STAGE, texture.STAGE, bake.STAGE, export.STAGE,
                             qa.STAGE)
BY_ID: dict[str, Stage] = {s.id: s for s in STAGES}
if tuple(BY_ID) != STAGE_IDS:
    raise ImportError(f"ops.stages declares {tuple(BY_ID)}, ops.engine.stage_ids orders {STAGE_IDS}")
