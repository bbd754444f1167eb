"""The Dagster code location loaded by ``workspace.yaml`` (``dagster dev`` from the repo root).

The per-photo assets, sensors and schedules are added here as the stages land; until then the
location loads and shows no assets.
"""

from dagster import Definitions

defs = Definitions()
