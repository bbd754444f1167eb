"""Everything the Dagster deployment is configured by, in one typed object read from the environment.

``MORPHEUS_PHOTO_DIR`` (watched folder), ``MORPHEUS_STORE`` (asset store root), ``MORPHEUS_PRESET``
(``ops.config.preset_names``: draft | standard | fast | paper), ``MORPHEUS_SET`` (pipeline overrides,
``;``-separated ``key=value``),
``MORPHEUS_SENSOR_MAX_NEW`` (photos added per sensor tick), ``MORPHEUS_SETTLE_S`` (seconds a file
must be untouched before it counts as uploaded), ``MORPHEUS_NIGHTLY_CRON``, ``MORPHEUS_TIMEZONE``,
``MORPHEUS_BATCH`` (photos per backfill run), ``MORPHEUS_BATCH_TOGETHER`` (``1``, the default: a
step of a GPU stage over several photos optimises them together, one prior forward per step for
all; ``0``: one after another), ``MORPHEUS_RETRIES``, ``MORPHEUS_RETRY_DELAY_S``,
``MORPHEUS_EXECUTOR`` (``in_process`` or ``multiprocess``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class OrchestrationSettings:
    photo_dir: str = "examples/photos"
    store_root: str = "outputs/dagster_store"
    preset: str = "draft"
    overrides: tuple[str, ...] = ()
    sensor_max_new_per_tick: int = 100
    sensor_interval_s: int = 30
    settle_seconds: float = 30.0
    nightly_cron: str = "0 2 * * *"
    timezone: str = "UTC"
    backfill_batch: int = 8
    batch_together: bool = True
    max_retries: int = 2
    retry_delay_s: float = 30.0
    executor: str = "in_process"

    def __post_init__(self) -> None:
        if self.sensor_max_new_per_tick < 1 or self.backfill_batch < 1:
            raise ValueError("MORPHEUS_SENSOR_MAX_NEW and MORPHEUS_BATCH must be >= 1")
        if self.max_retries < 0 or self.retry_delay_s < 0 or self.settle_seconds < 0:
            raise ValueError("MORPHEUS_RETRIES, MORPHEUS_RETRY_DELAY_S and MORPHEUS_SETTLE_S must be >= 0")
        if self.executor not in ("in_process", "multiprocess"):
            raise ValueError(f"MORPHEUS_EXECUTOR={self.executor!r}: expected in_process or multiprocess")

    @classmethod
    def from_env(cls, env: Mapping[str, str] | None = None) -> OrchestrationSettings:
        env = os.environ if env is None else env
        d = cls()

        def get(name: str, default: object, cast: type) -> object:
            raw = env.get(name)
            if raw is None or raw == "":
                return default
            try:
                return cast(raw)
            except ValueError as exc:
                raise ValueError(f"{name}={raw!r}: expected {cast.__name__}") from exc

        def flag(name: str, default: bool) -> bool:
            raw = env.get(name, "").strip().lower()
            if raw == "":
                return default
            if raw not in ("1", "true", "yes", "on", "0", "false", "no", "off"):
                raise ValueError(f"{name}={raw!r}: expected 1 or 0")
            return raw in ("1", "true", "yes", "on")

        overrides = tuple(p.strip() for p in env.get("MORPHEUS_SET", "").split(";") if p.strip())
        return cls(
            photo_dir=str(Path(str(get("MORPHEUS_PHOTO_DIR", d.photo_dir, str))).absolute()),
            store_root=str(Path(str(get("MORPHEUS_STORE", d.store_root, str))).absolute()),
            preset=str(get("MORPHEUS_PRESET", d.preset, str)),
            overrides=overrides,
            sensor_max_new_per_tick=int(get("MORPHEUS_SENSOR_MAX_NEW", d.sensor_max_new_per_tick, int)),
            sensor_interval_s=int(get("MORPHEUS_SENSOR_INTERVAL_S", d.sensor_interval_s, int)),
            settle_seconds=float(get("MORPHEUS_SETTLE_S", d.settle_seconds, float)),
            nightly_cron=str(get("MORPHEUS_NIGHTLY_CRON", d.nightly_cron, str)),
            timezone=str(get("MORPHEUS_TIMEZONE", d.timezone, str)),
            backfill_batch=int(get("MORPHEUS_BATCH", d.backfill_batch, int)),
            batch_together=flag("MORPHEUS_BATCH_TOGETHER", d.batch_together),
            max_retries=int(get("MORPHEUS_RETRIES", d.max_retries, int)),
            retry_delay_s=float(get("MORPHEUS_RETRY_DELAY_S", d.retry_delay_s, float)),
            executor=str(get("MORPHEUS_EXECUTOR", d.executor, str)),
        )
