"""When an optimising stage may end before its schedule: its scene has stopped improving.

The signal is the stage's own run log: the reference-view PSNR, measured every ``log_every``
steps by a deterministic render. The guidance loss is not used: SDS/VSD losses are surrogates
whose value does not fall as the object improves (only their gradient means anything), and the
stages' own terms (mask, regularisers) are part of what the reference PSNR already sums up.

Rule, checked at each log row once ``early_stop_min_share`` of the schedule has run: the best PSNR
of the last ``early_stop_patience`` share of the schedule must beat the best before that window by
``early_stop_min_gain_db``; when it does not, the stage stops. Taking the best of a window makes
the rule robust to the noise of single rows. The decision reads only the logged history, which
checkpoints hold, so a resumed run stops at the same step as an uninterrupted one.

A stage that ran its whole schedule made what any early-stopping setting would have made, so its
fingerprint leaves those settings out (``whole_schedule_record``): upgrading to early stopping, or
turning it off, never makes a finished full-schedule output stale.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ops.engine.loop import LoopConfig

EARLY_STOP_FIELDS = ("early_stop", "early_stop_patience", "early_stop_min_share", "early_stop_min_gain_db")
METRIC = "ref_psnr"


def converged(history: Sequence[dict[str, Any]], done: int, config: LoopConfig, metric: str = METRIC) -> bool:
    """Whether the stage may stop after step ``done`` (see the module docstring)."""
    if not config.early_stop or done >= config.steps or done < config.early_stop_min_share * config.steps:
        return False
    window_start = done - max(1, round(config.early_stop_patience * config.steps))
    recent = [row[metric] for row in history if row["step"] > window_start and _finite(row.get(metric))]
    before = [row[metric] for row in history if row["step"] <= window_start and _finite(row.get(metric))]
    if not recent or not before:
        return False
    return max(recent) - max(before) < config.early_stop_min_gain_db


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def whole_schedule_record(record: dict[str, Any]) -> dict[str, Any]:
    """A stage's config record without the early-stopping settings of its loops (any ``loop`` table)."""
    out = copy.deepcopy(record)
    stack = [out]
    while stack:
        node = stack.pop()
        loop = node.get("loop")
        if isinstance(loop, dict):
            for name in EARLY_STOP_FIELDS:
                loop.pop(name, None)
        stack.extend(v for v in node.values() if isinstance(v, dict))
    return out
