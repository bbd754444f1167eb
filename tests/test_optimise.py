"""The guarded, resumable loop on a small real regression task: exact resume, NaN guards, restores."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest
import torch
from torch import nn

from assets_store.checkpoints import Checkpoints
from ops.engine.early_stop import converged
from ops.engine.loop import BadStep, LoopConfig, StepOutput, run_loop


class _InfGradient(torch.autograd.Function):
    """Zero in the forward pass, +inf gradient in the backward: a finite loss with a broken gradient."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor) -> torch.Tensor:
        ctx.shape = x.shape
        return x.sum() * 0.0

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
        return torch.full(ctx.shape, float("inf"))


class Regression:
    """Fit an MLP to a random function with minibatches drawn from the loop's generator.

    ``poison`` maps step → what goes wrong there: "loss" (NaN loss), "grad" (Inf gradient),
    "prior" (a prior reported NaN values), "bad" (the step raises BadStep)."""

    def __init__(self, seed: int, poison: dict[int, str] | None = None, fused: bool = False) -> None:
        g = torch.Generator().manual_seed(seed)
        self.x = torch.randn(256, 4, generator=g)
        self.y = torch.sin(self.x @ torch.randn(4, 2, generator=g))
        torch.manual_seed(seed)
        self.net = nn.Sequential(nn.Linear(4, 16), nn.Tanh(), nn.Linear(16, 2))
        # fused: the optimiser skips bad steps on a device flag; else the loop asks the host
        self.opt = torch.optim.Adam(self.net.parameters(), lr=1e-2, fused=fused)
        self.poison = poison or {}
        self.after: list[bool] = []

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {"net": self.opt}

    def step(self, step: int, generator: torch.Generator) -> StepOutput:
        kind = self.poison.get(step)
        if kind == "bad":
            raise BadStep("no surface")
        idx = torch.randint(0, 256, (32,), generator=generator)
        loss = (self.net(self.x[idx]) - self.y[idx]).pow(2).mean()
        if kind == "loss":
            loss = loss * float("nan")
        if kind == "grad":
            loss = loss + _InfGradient.apply(self.net[0].weight)
        return StepOutput(loss, {"mse": loss.detach()}, 5 if kind == "prior" else 0)

    def after_step(self, ok: torch.Tensor | bool) -> None:
        self.after.append(bool(ok))

    def state(self) -> dict[str, Any]:
        return {"net": self.net.state_dict(), "opt": self.opt.state_dict()}

    def load_state(self, state: Mapping[str, Any]) -> None:
        self.net.load_state_dict(state["net"])
        self.opt.load_state_dict(state["opt"])

    def evaluate(self, done: int) -> dict[str, float]:
        with torch.no_grad():
            mse = float((self.net(self.x) - self.y).pow(2).mean())
        return {"full_mse": mse, "fit_db": -10.0 * math.log10(max(mse, 1e-12))}

    def stop_early(self, history: list[dict[str, Any]], done: int, config: LoopConfig) -> bool:
        return converged(history, done, config, "fit_db")


def _run(task: Regression, steps: int, ckpt: Path | None, seed: int = 3, every: int = 5,
         early_stop: bool = False) -> Any:
    return run_loop(task, LoopConfig(steps, checkpoint_every=every, log_every=1, grad_clip=None, early_stop=early_stop),
                    torch.Generator().manual_seed(seed), "test", ckpt)


def _params(task: Regression) -> list[torch.Tensor]:
    return [p.detach().clone() for p in task.net.parameters()]


def test_loop_learns_and_logs_every_step() -> None:
    task = Regression(0)
    res = _run(task, 150, None)
    assert res.history[-1]["full_mse"] < 0.5 * res.history[0]["full_mse"]
    assert [r["step"] for r in res.history] == list(range(1, 151))
    assert res.guards.skipped == 0 and res.resumed_from is None


def test_resume_from_checkpoint_is_bit_identical(tmp_path: Path) -> None:
    full = Regression(1)
    _run(full, 23, None)
    # An interrupted run: stop after 12 steps (checkpoints at 5 and 10), then a fresh process-like
    # restart with fresh objects and a differently seeded generator that the checkpoint overrides.
    first = Regression(1)
    _run(first, 12, tmp_path)
    assert Checkpoints(tmp_path).steps()[-1] == 10
    second = Regression(1)
    with torch.no_grad():  # prove the state comes from the checkpoint, not the constructor
        for p in second.net.parameters():
            p.add_(torch.randn_like(p))
    res = _run(second, 23, tmp_path, seed=999)
    assert res.resumed_from == 10 and res.steps_run == 13
    for a, b in zip(_params(full), _params(second), strict=True):
        assert torch.equal(a, b)
    assert [r["step"] for r in res.history] == list(range(1, 24))


FUSED = pytest.mark.parametrize("fused", [False, True], ids=["host-skip", "device-skip"])


@FUSED
@pytest.mark.parametrize("kind,counter", [("loss", "nonfinite_loss"), ("grad", "nonfinite_grad"),
                                          ("prior", "nonfinite_prior"), ("bad", "bad_step")])
def test_bad_steps_are_skipped_and_counted(kind: str, counter: str, fused: bool, tmp_path: Path) -> None:
    task = Regression(2, {4: kind, 9: kind}, fused)
    res = _run(task, 15, tmp_path)
    assert getattr(res.guards, counter) == 2 and res.guards.skipped == 2 and res.guards.restores == 0
    assert task.after.count(False) == 2
    assert all(torch.isfinite(p).all() for p in task.net.parameters())
    rows = {r["step"]: r for r in res.history}
    assert rows[5]["ok"] is False and rows[6]["ok"] is True
    if kind == "loss":
        assert rows[5]["loss"] is None  # a non-finite value is logged as missing, never as NaN


@FUSED
def test_a_skipped_step_changes_nothing(fused: bool) -> None:
    clean, poisoned = Regression(4, fused=fused), Regression(4, {0: "grad"}, fused)
    gen = torch.Generator().manual_seed(5)
    run_loop(poisoned, LoopConfig(1, log_every=1, grad_clip=None), gen, "t")
    for a, b in zip(_params(clean), _params(poisoned), strict=True):
        assert torch.equal(a, b)
    assert not poisoned.opt.state_dict()["state"] or float(poisoned.opt.state_dict()["state"][0]["step"]) == 0


@pytest.mark.parametrize("kind", ["loss", "grad", "prior", "bad"])
def test_guards_read_every_n_steps_give_the_same_run_as_every_step(kind: str) -> None:
    """The device-skip path reads its guards at log rows only; skipping is decided on the device, so
    the parameters, optimiser state and counts equal those of a run that reads them every step."""
    runs = []
    for log_every in (1, 7):
        task = Regression(9, {3: kind, 4: kind, 11: kind}, fused=True)
        res = run_loop(task, LoopConfig(20, log_every=log_every, grad_clip=1.0, early_stop=False),
                       torch.Generator().manual_seed(2), "t")
        runs.append((task, res))
    (a, ra), (b, rb) = runs
    assert ra.guards == rb.guards and ra.guards.skipped == 3 and ra.guards.restores == 0
    for x, y in zip(_params(a), _params(b), strict=True):
        assert torch.equal(x, y)
    assert float(a.opt.state_dict()["state"][0]["step"]) == float(b.opt.state_dict()["state"][0]["step"]) == 17
    assert a.after == b.after and a.after.count(False) == 3


@FUSED
def test_repeated_failures_restore_the_last_good_state(fused: bool, tmp_path: Path) -> None:
    task = Regression(6, {s: "loss" for s in range(12, 18)}, fused)
    res = _run(task, 20, tmp_path, every=10)
    assert res.guards.nonfinite_loss == 6 and res.guards.restores == 2  # 3 bad in a row → restore, twice
    assert all(torch.isfinite(p).all() for p in task.net.parameters())


@FUSED
def test_parameters_that_turn_nonfinite_are_rolled_back(fused: bool) -> None:
    task = Regression(7, fused=fused)
    real_step = task.opt.step

    def exploding_step(*args: Any, **kwargs: Any) -> Any:
        out = real_step(*args, **kwargs)
        if len(task.after) == 3:
            with torch.no_grad():
                task.net[2].bias.fill_(float("inf"))
        return out

    task.opt.step = exploding_step  # type: ignore[method-assign]
    res = run_loop(task, LoopConfig(6, log_every=1, grad_clip=None), torch.Generator().manual_seed(1), "t")
    assert res.guards.nonfinite_param == 1
    assert all(torch.isfinite(p).all() for p in task.net.parameters())


def test_gradient_clipping_bounds_the_update() -> None:
    a, b = Regression(8), Regression(8)
    run_loop(a, LoopConfig(1, grad_clip=None), torch.Generator().manual_seed(1), "t")
    run_loop(b, LoopConfig(1, grad_clip=1e-6), torch.Generator().manual_seed(1), "t")
    # Adam normalises the first step, so clipping shows in the moments, not the step size.
    ma = a.opt.state_dict()["state"][0]["exp_avg"].abs().max()
    mb = b.opt.state_dict()["state"][0]["exp_avg"].abs().max()
    assert mb < 1e-5 * ma


def test_loop_config_rejects_nonsense() -> None:
    with pytest.raises(ValueError):
        LoopConfig(-1)
    with pytest.raises(ValueError):
        LoopConfig(10, checkpoint_every=0)
    with pytest.raises(ValueError):
        LoopConfig(10, grad_clip=0.0)
    with pytest.raises(ValueError, match="precision"):
        LoopConfig(10, precision="float8")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="fp16_loss_scale"):
        LoopConfig(10, fp16_loss_scale=float("inf"))


@FUSED
@pytest.mark.parametrize("precision", ["bfloat16", "float16"])
def test_half_precision_steps_learn_and_keep_float32_parameters(precision: str, fused: bool) -> None:
    task = Regression(5, fused=fused)
    res = run_loop(task, LoopConfig(150, log_every=1, grad_clip=None, precision=precision),  # type: ignore[arg-type]
                   torch.Generator().manual_seed(3), "test")
    assert res.guards.skipped == 0
    assert res.history[-1]["full_mse"] < 0.5 * res.history[0]["full_mse"]
    assert all(p.dtype == torch.float32 and bool(torch.isfinite(p).all()) for p in task.net.parameters())


def test_float16_loss_scaling_keeps_tiny_gradients_and_unscales_them() -> None:
    """A loss of 1e-4·‖net(x)‖² has float16 activation gradients below the subnormal range
    without scaling; with the default scale the first update's gradients match float32's."""

    class Tiny(Regression):
        def step(self, step: int, generator: torch.Generator) -> StepOutput:
            loss = 1e-7 * self.net(self.x[:32]).pow(2).sum()
            return StepOutput(loss, {}, 0)

    grads = {}
    for precision, scale in (("float32", 1.0), ("float16", 1024.0), ("float16", 1.0)):
        task = Tiny(2)
        grabbed: list[torch.Tensor] = []
        task.opt.step = lambda *a, _t=task, _g=grabbed, **k: _g.append(_t.net[0].weight.grad.clone())  # type: ignore
        run_loop(task, LoopConfig(1, grad_clip=None, precision=precision, fp16_loss_scale=scale),  # type: ignore
                 torch.Generator().manual_seed(0), "t")
        grads[(precision, scale)] = grabbed[0]
    ref = grads[("float32", 1.0)]
    scaled = grads[("float16", 1024.0)]
    assert torch.allclose(scaled, ref, rtol=0.05, atol=1e-3 * float(ref.abs().max()))
    unscaled_error = float((grads[("float16", 1.0)] - ref).abs().max())
    assert unscaled_error > 10 * float((scaled - ref).abs().max())


@FUSED
def test_float16_loss_scale_backs_off_after_an_overflow_and_the_run_still_learns(fused: bool) -> None:
    """A loss whose scaled gradients overflow float16 (65504): the first steps are skipped while the
    scale halves, then the run learns."""

    class Loud(Regression):
        def step(self, step: int, generator: torch.Generator) -> StepOutput:
            out = super().step(step, generator)
            return StepOutput(out.loss * 3e3, out.terms, 0)

    task = Loud(4, fused=fused)
    config = LoopConfig(200, log_every=10 if fused else 1, grad_clip=None, precision="float16", max_bad_steps=50)
    res = run_loop(task, config,
                   torch.Generator().manual_seed(3), "test")
    assert 1 <= res.guards.nonfinite_grad <= 16, res.guards
    assert res.history[-1]["full_mse"] < 0.5 * res.history[0]["full_mse"]
