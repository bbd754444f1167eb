"""A temporary Dagster deployment over a folder of photos, with the tiny pipeline configuration."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable
from pathlib import Path

import dagster as dg
import pytest

from ops.engine.progress import ProgressEvent
from orchestration.definitions import JOB, build_definitions
from orchestration.partitions import PHOTOS
from orchestration.settings import OrchestrationSettings
from tests.pipeline_helpers import PHOTOS as EXAMPLES
from tests.pipeline_helpers import cli_overrides, tiny_config

TINY = tuple(cli_overrides(tiny_config())[1::2])  # the "key=value" halves of the --set pairs


def photo_folder(root: Path, names: Iterable[str]) -> Path:
    folder = root / "photos"
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(EXAMPLES / name, folder / name)
    return folder


def settings(root: Path, **changes: object) -> OrchestrationSettings:
    base = {"photo_dir": str(root / "photos"), "store_root": str(root / "store"), "overrides": TINY,
            "settle_seconds": 0.0, "max_retries": 0, "retry_delay_s": 0.0}
    return OrchestrationSettings(**{**base, **changes})


def run_job(defs: dg.Definitions, instance: dg.DagsterInstance, keys: list[str],
            assets: list[str] | None = None) -> dg.ExecuteInProcessResult:
    """One run over ``keys``: a single partition, or a batch (what a multi-run backfill launches);
    every asset, or only ``assets``."""
    instance.add_dynamic_partitions(PHOTOS, keys)
    job = defs.resolve_job_def(JOB)
    selection = None if assets is None else [dg.AssetKey(a) for a in assets]
    if len(keys) == 1:
        return job.execute_in_process(partition_key=keys[0], instance=instance, raise_on_error=False,
                                      asset_selection=selection)
    tags = {"dagster/asset_partition_range_start": keys[0], "dagster/asset_partition_range_end": keys[-1]}
    return job.execute_in_process(tags=tags, instance=instance, raise_on_error=False, asset_selection=selection)


def materializations(result: dg.ExecuteInProcessResult) -> dict[tuple[str, str | None], dict]:
    """(asset, partition) → metadata of the run's materialisations (the last one wins)."""
    out = {}
    for e in result.all_events:
        if e.event_type_value == "ASSET_MATERIALIZATION":
            m = e.event_specific_data.materialization
            out[(m.asset_key.to_user_string(), m.partition)] = m.metadata
    return out


def check_evaluations(result: dg.ExecuteInProcessResult) -> list:
    return [e.event_specific_data for e in result.all_events if e.event_type_value == "ASSET_CHECK_EVALUATION"]


def build(root: Path, **changes: object) -> dg.Definitions:
    return build_definitions(settings=settings(root, **changes))


class Fault:
    """A crash injected into a running stage through its progress hook (the loop reports every
    step in the tiny configuration, before that step's checkpoint is written)."""

    def __init__(self, stage_label: str, at_step: int, once: bool) -> None:
        self.stage_label, self.at_step, self.once = stage_label, at_step, once
        self.fired: list[int] = []
        self.armed = True

    def disarm(self) -> None:
        self.armed = False

    def check(self, event: ProgressEvent) -> None:
        if self.armed and event.stage == self.stage_label and event.step >= self.at_step:
            self.fired.append(event.step)
            if self.once:
                self.armed = False
            raise RuntimeError(f"injected fault at step {event.step}: the machine went away")


def inject_fault(monkeypatch: pytest.MonkeyPatch, stage_label: str, at_step: int, once: bool = False) -> Fault:
    """Make ``stage_label`` (``"<key>:<stage>"``) crash at ``at_step`` in every Dagster stage asset."""
    import orchestration.assets as assets_module

    fault = Fault(stage_label, at_step, once)
    real = assets_module._logging_progress

    def wrapped(context: dg.AssetExecutionContext) -> Callable[[ProgressEvent], None]:
        report = real(context)

        def hook(event: ProgressEvent) -> None:
            fault.check(event)
            report(event)

        return hook

    monkeypatch.setattr(assets_module, "_logging_progress", wrapped)
    return fault


def job_from_env() -> dg.JobDefinition:
    """The photos job for the settings in the environment (``dg.reconstructable`` needs a module-level
    function: re-execution from failure rebuilds the job in a new process)."""
    return build_definitions(settings=OrchestrationSettings.from_env()).resolve_job_def(JOB)
