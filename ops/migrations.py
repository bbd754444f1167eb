"""Every name the product changed after users had stores, configs and Dagster history with the old
one: the tables here, and where the code that applies each lives.

This module imports nothing, so every layer (the command line, the report, the store, Dagster) can
read it without loading torch. What each table is applied by:

- ``RENAMED_STAGES`` (stage ids before every stage got one id): store folders and fingerprint inputs
  by ``ops.engine.store_layout`` (store layout 1 → 2, once per store); catalog columns and QA reports
  by ``ops.reporting.stage_columns`` and ``ops.reporting.catalog_rows``; any name a user types, and the
  QA reports' stage names, by ``current_stage_id`` below.
- ``RENAMED_KEYS`` (config keys): ``--set`` and ``MORPHEUS_SET`` by ``ops.config.presets.current_key``,
  with a warning naming the new key.
- ``RENAMED_ASSETS`` (Dagster asset keys): materialisations carried over by
  ``orchestration.history.migrate_history``.
- ``ADDED_SETTINGS`` (settings added after outputs existed, with their defaults): left out of a stage's
  config record while at their default by ``ops.pipeline.photo_run.stage_config_record``, so finished
  outputs keep their fingerprints.
"""

from __future__ import annotations

from typing import Any

RENAMED_STAGES = {"nerf_fit": "nerf", "texture_refine": "texture", "uv_bake": "bake"}
"""Stage id before the renaming → stage id."""


def current_stage_id(name: str) -> str:
    """The stage id for ``name``, which may be an id from before the renaming."""
    return RENAMED_STAGES.get(name, name)


RENAMED_KEYS = {"prepare.": "reference.prepare.", "plan.": "reference.plan.",
                "dmtet.texture.": "dmtet.texture_field.", "bake.bake.": "bake.map."}
"""Config key prefix before the renaming → current prefix."""

RENAMED_ASSETS = {"nerf_field": "nerf", "dmtet_mesh": "dmtet", "refined_texture": "texture", "uv_asset": "bake",
                  "qa_report": "qa"}
"""Dagster asset key before the renaming → stage id (``reference`` kept its key)."""

ADDED_SETTINGS: dict[str, Any] = {"phases": []}
"""Setting name → its default as a config record holds it (render phases: 2026-12-07)."""
