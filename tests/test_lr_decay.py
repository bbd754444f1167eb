"""The loop's learning-rate decay (``LoopConfig.lr_final``, ``ops.engine.learning_rate``): its shape, that
the loop applies it, that a resumed run decays alike, that it lowers the noise floor of noisy gradients,
and that its defaults leave finished outputs' fingerprints alone."""

from __future__ import annotations

from collections.abc import Mapping
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch import nn

from ops.engine.learning_rate import lr_multiplier
from ops.engine.loop import LoopConfig, StepOutput, run_loop
from ops.pipeline.photo_run import stage_config_record
from tests.test_optimise import Regression


def test_the_multiplier_holds_then_falls_by_a_half_cosine_to_lr_final() -> None:
    rng = np.random.default_rng()
    for _ in range(20):
        steps = int(rng.integers(10, 500))
        cfg = LoopConfig(steps, lr_final=float(rng.uniform(0.01, 0.9)), lr_decay_start=float(rng.uniform(0, 0.9)))
        m = [lr_multiplier(s, steps, cfg.lr_final, cfg.lr_decay_start) for s in range(steps)]
        start = cfg.lr_decay_start * steps
        assert all(v == 1.0 for s, v in enumerate(m) if s <= start)
        assert all(b <= a + 1e-12 for a, b in pairwise(m))  # never rises
        assert min(m) >= cfg.lr_final - 1e-12
        if steps - 1 > start:
            assert m[-1] == pytest.approx(cfg.lr_final)
    assert {lr_multiplier(s, 50, 1.0, 0.5) for s in range(50)} == {1.0}  # the default: constant


@pytest.mark.parametrize("bad", [{"lr_final": 0.0}, {"lr_final": 1.5}, {"lr_decay_start": 1.0},
                                 {"lr_decay_start": -0.1}])
def test_settings_outside_their_range_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="lr_final"):
        LoopConfig(10, **bad)


class _Recording(Regression):
    """The regression task that records its optimiser's rate at every step."""

    def __init__(self, seed: int, kill_at: int | None = None) -> None:
        super().__init__(seed)
        self.rates: list[float] = []
        self.kill_at = kill_at

    def step(self, step: int, generator: torch.Generator) -> StepOutput:
        if step == self.kill_at:
            raise KeyboardInterrupt(f"killed at {step}")
        self.rates.append(self.opt.param_groups[0]["lr"])
        return super().step(step, generator)


CFG = LoopConfig(40, checkpoint_every=8, log_every=4, grad_clip=None, lr_final=0.1, lr_decay_start=0.25)


def test_the_loop_sets_every_rate_from_its_configured_one() -> None:
    task = _Recording(2)
    run_loop(task, CFG, torch.Generator().manual_seed(0), "test")
    assert task.rates == pytest.approx([1e-2 * lr_multiplier(s, 40, 0.1, 0.25) for s in range(40)])
    assert task.opt.param_groups[0]["base_lr"] == 1e-2


def test_a_killed_run_resumes_to_the_same_parameters(tmp_path: Path) -> None:
    whole = _Recording(3)
    run_loop(whole, CFG, torch.Generator().manual_seed(5), "test")
    with pytest.raises(KeyboardInterrupt):
        run_loop(_Recording(3, kill_at=29), CFG, torch.Generator().manual_seed(5), "test", tmp_path)
    resumed = _Recording(3)
    res = run_loop(resumed, CFG, torch.Generator().manual_seed(5), "test", tmp_path)
    assert res.resumed_from == 24
    assert resumed.rates == pytest.approx(whole.rates[24:])  # the checkpoint's rates, not the constructor's
    for a, b in zip(whole.net.parameters(), resumed.net.parameters(), strict=True):
        assert torch.equal(a, b)


class _NoisyQuadratic:
    """Minimise |x|² from gradients with unit noise: at a constant rate Adam's iterate keeps a spread
    set by the rate (the noise floor a stochastic prior leaves); a decaying rate shrinks it."""

    def __init__(self, seed: int) -> None:
        self.x = nn.Parameter(torch.randn(256, generator=torch.Generator().manual_seed(seed)))
        self.opt = torch.optim.Adam([self.x], lr=0.05)

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"x": self.opt}

    def step(self, step: int, generator: torch.Generator) -> StepOutput:
        noise = torch.randn(256, generator=generator)
        loss = 0.5 * self.x.pow(2).sum() + (noise * self.x).sum()
        return StepOutput(loss, {})

    def after_step(self, ok: torch.Tensor | bool) -> None:
        pass

    def state(self) -> dict[str, Any]:
        return {"x": self.x.detach().clone(), "opt": self.opt.state_dict()}

    def load_state(self, state: Mapping[str, Any]) -> None:
        with torch.no_grad():
            self.x.copy_(state["x"])
        self.opt.load_state_dict(state["opt"])

    def evaluate(self) -> dict[str, float]:
        return {"rms": float(self.x.detach().pow(2).mean().sqrt())}

    def stop_early(self, history: list[dict[str, Any]], done: int, config: LoopConfig) -> bool:
        return False


def test_a_decaying_rate_lowers_the_noise_floor() -> None:
    seed = int(np.random.default_rng().integers(1 << 30))
    finals = {}
    for lr_final in (1.0, 0.1):
        task = _NoisyQuadratic(seed)
        cfg = LoopConfig(600, log_every=600, grad_clip=None, lr_final=lr_final)
        finals[lr_final] = run_loop(task, cfg, torch.Generator().manual_seed(seed), "test").history[-1]["rms"]
    # Constant: the iterate wanders by about the rate; decayed to a tenth, by well under half of it.
    assert finals[0.1] < 0.5 * finals[1.0], finals


def test_default_rates_leave_a_stage_s_config_record_as_before() -> None:
    assert not {"lr_final", "lr_decay_start"} & set(stage_config_record({"loop": LoopConfig(10)})["loop"])
    record = stage_config_record({"loop": LoopConfig(10, lr_final=0.1)})["loop"]
    assert record["lr_final"] == 0.1
