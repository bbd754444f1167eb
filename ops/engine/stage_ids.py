"""The stage ids in pipeline order, and the ids stages had before they were unified.

This module imports nothing, so the command line and the HTML report can name stages without
loading torch; ``ops.stages`` refuses to import when its declarations disagree with this order.
"""

STAGE_IDS = ("reference", "nerf", "dmtet", "texture", "bake", "qa")

# Store folders, fingerprint inputs, catalog columns and QA reports written before the renaming use
# these ids; ``ops.engine.store_layout`` migrates stores, readers map old names with ``current_stage_id``.
RENAMED_STAGES = {"nerf_fit": "nerf", "texture_refine": "texture", "uv_bake": "bake"}


def current_stage_id(name: str) -> str:
    """The stage id for ``name``, which may be an id from before the renaming."""
    return RENAMED_STAGES.get(name, name)
