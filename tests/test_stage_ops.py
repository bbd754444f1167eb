"""``benchmarks.stage_speed``'s operator count: per steady-state step, charged to our code's lines."""

from __future__ import annotations

import torch

from benchmarks.stage_speed import OpCounter, ops_per_step
from ops.engine.loop import LoopConfig, run_loop
from tests.test_optimise import Regression


def warmed(gen: torch.Generator) -> Regression:
    """Past Adam's first step, which creates its moments (stage_speed counts after the timed steps)."""
    task = Regression(1)
    run_loop(task, LoopConfig(2, log_every=10_000, grad_clip=None), gen, "warm-up")
    return task


def test_the_loop_set_up_and_log_row_cancel_out_of_the_per_step_count() -> None:
    gen = torch.Generator().manual_seed(2)
    two, four = (ops_per_step(warmed(gen), gen, sites=50, extra=n) for n in (2, 4))
    assert two["aten_ops_per_step"] == four["aten_ops_per_step"] > 0  # the same step, however many
    with OpCounter() as one_step_loop:
        run_loop(warmed(gen), LoopConfig(1, log_every=10_000, grad_clip=None), gen, "ops")
    assert one_step_loop.calls > 2 * two["aten_ops_per_step"]  # the set-up copy and the log row's evaluation
    assert sum(two["op_sites"].values()) == two["aten_ops_per_step"]  # every op charged to one site
    # The test task's own operators are charged to the loop line that called it: tests/ is not our code.
    assert all(site.startswith(("ops/", "morpheus_core/")) for site in two["op_sites"])
    assert any(site.startswith("ops/engine/loop.py:") for site in two["op_sites"])
