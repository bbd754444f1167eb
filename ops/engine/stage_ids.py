"""The stage ids in pipeline order, and the current id of a name from before they were unified.

This module imports only ``ops.migrations`` (which imports nothing), so the command line and the HTML
report can name stages without loading torch; ``ops.stages`` refuses to import when its declarations
disagree with this order.
"""

from ops.migrations import RENAMED_STAGES

STAGE_IDS = ("reference", "nerf", "dmtet", "texture", "bake", "export", "qa")


def current_stage_id(name: str) -> str:
    """The stage id for ``name``, which may be an id from before the renaming."""
    return RENAMED_STAGES.get(name, name)
