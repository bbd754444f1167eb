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

The unseen sides (``early_stop_watch_sides``, on by default when early stopping is on): the reference
view converges before the sides the photo does not show, so stopping on it alone cost 0.5 dB of GLB
novel-view PSNR (``benchmarks/results/early_stop_paper10_h200.md``). ``SideWatch`` renders fixed
held-out views (both sides and the back, 15° up) at every log row and logs how coherently they still
move over the patience window: ``sides_drift`` = |R_now − R_start|² / Σ|R_i − R_i−1|², the squared net
change of the renders over the window against the sum of their squared changes between log rows. Renders
with millions of pixels that still drift towards something give about n (the n changes add up), a random
walk 1 (independent changes add in quadrature), renders jittering around where they have settled 1/n. The
stage may stop only when the sides move no more coherently than a random walk, ``sides_drift`` ≤ 1: a
threshold set by that rationale, not fitted to a benchmark. Fewer than three intervals in the window say
nothing, so the rule waits.
"""

from __future__ import annotations

import copy
import itertools
import math
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from morpheus_core.cameras import Cameras, orbit

if TYPE_CHECKING:
    from ops.engine.loop import LoopConfig

EARLY_STOP_FIELDS = ("early_stop", "early_stop_patience", "early_stop_min_share", "early_stop_min_gain_db",
                     "early_stop_watch_sides")
METRIC = "ref_psnr"
SIDES_METRIC = "sides_drift"
SIDE_VIEWS = ((15.0, 90.0), (15.0, 180.0), (15.0, -90.0))
"""(elevation, azimuth) in degrees of the held-out views: both sides and the back, where the photo says least."""
SIDE_VIEW_SIZE = 64
"""Pixels per side of the held-out renders: enough to see a side change, small enough to keep a window of them
in every checkpoint (3 views × 3 × 64² floats, 147 kB a row)."""
MIN_INTERVALS = 3
"""Log intervals the window must hold before ``sides_drift`` means anything (with one, net = step: always 1)."""


def window_steps(config: LoopConfig) -> int:
    """The patience window in steps."""
    return max(1, round(config.early_stop_patience * config.steps))


def converged(history: Sequence[dict[str, Any]], done: int, config: LoopConfig, metric: str = METRIC,
              sides: str | None = None) -> bool:
    """Whether the stage may stop after step ``done`` (see the module docstring). ``sides``: the column of
    the task's ``sides_drift`` when it watches the unseen sides (None: the reference view decides alone)."""
    if not config.early_stop or done >= config.steps or done < config.early_stop_min_share * config.steps:
        return False
    window_start = done - window_steps(config)
    recent = [row[metric] for row in history if row["step"] > window_start and _finite(row.get(metric))]
    before = [row[metric] for row in history if row["step"] <= window_start and _finite(row.get(metric))]
    if not recent or not before or max(recent) - max(before) >= config.early_stop_min_gain_db:
        return False
    if sides is None or not config.early_stop_watch_sides:
        return True
    drift = history[-1].get(sides) if history and history[-1]["step"] == done else None
    return _finite(drift) and drift <= 1.0


class SideWatch:
    """The held-out views' renders at the log rows of the last patience window, and the two numbers they
    give each row: ``sides_change`` (RMS change since the previous row) and ``sides_drift`` (see the module
    docstring; NaN until the window holds ``MIN_INTERVALS`` intervals). Kept in the task's checkpointed state,
    so a resumed run logs, and stops, as an uninterrupted one does."""

    def __init__(self, window: int, reference: Cameras) -> None:
        self.window = window
        # At the reference camera's distance and field of view: the object fills the side views as it fills the photo.
        self.cameras = orbit([e for e, _ in SIDE_VIEWS], [a for _, a in SIDE_VIEWS], float(reference.distance[0]),
                             math.degrees(float(reference.fov_y[0])), reference.near,
                             reference.far).to(reference.device)
        self.rows: list[tuple[int, Tensor]] = []

    def observe(self, done: int, renders: Tensor) -> dict[str, float]:
        """Take the held-out renders (V×3×H×W) of the log row at step ``done``; its two numbers."""
        renders = renders.detach().float().cpu()
        if not torch.isfinite(renders).all():
            return {"sides_change": math.nan, SIDES_METRIC: math.nan}  # a broken render says nothing
        self.rows.append((done, renders))
        start = done - self.window
        # The newest row at or before the window's start anchors the net change; older rows are not needed again.
        anchor = max((i for i, (step, _) in enumerate(self.rows) if step <= start), default=None)
        if anchor is not None:
            del self.rows[:anchor]
        sets = [r for _, r in self.rows]
        change = math.sqrt(float((sets[-1] - sets[-2]).pow(2).mean())) if len(sets) > 1 else math.nan
        drift = math.nan
        if anchor is not None and len(sets) > MIN_INTERVALS:
            steps = sum(float((b - a).pow(2).sum()) for a, b in itertools.pairwise(sets))
            net = float((sets[-1] - sets[0]).pow(2).sum())
            drift = net / steps if steps > 0 else 0.0  # renders that no longer change at all have settled
        return {"sides_change": change, SIDES_METRIC: drift}

    def state(self) -> dict[str, Any]:
        return {"steps": [step for step, _ in self.rows], "renders": [r for _, r in self.rows]}

    def load_state(self, state: Mapping[str, Any]) -> None:
        self.rows = [(int(step), r.clone()) for step, r in zip(state["steps"], state["renders"], strict=True)]


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
