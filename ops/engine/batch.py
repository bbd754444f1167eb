"""Several objects optimised together through one stage loop: one prior forward serves them all.

The priors' forward passes are launch-bound on a large GPU (DESIGN.md §7: the Zero123 forward
costs the same for 1 and 16 objects), so a catalog is fastest when every step renders each
object, concatenates the renders and runs the guidance once. ``BatchTask`` is a ``StageTask``
over the per-object tasks of one stage:

- each object keeps its own modules, Adam (so gradient clipping stays per object), LoRA adapter
  (rows of the shared UNet, ``ObjectLoras``) and random generator, and the guidance takes its
  expectations per object (``hybrid_guidance(objects=N)``): an object's updates are the ones it
  would get alone, up to floating-point summation order (a test checks this);
- an object whose step is bad (empty surface, non-finite render) sits that step out while the
  others go on; its count is reported per object;
- an object whose scene has converged (``ops.engine.early_stop``, on its own log columns) stops
  there: it is no longer rendered, guided or evaluated, and the batch ends when all have stopped;
- the loop (``run_loop``) is unchanged: checkpoints hold every object's state and generator, so
  a killed batch resumes exactly when it is re-run with the same objects.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from morpheus_core.guidance.hybrid import PriorBinding, hybrid_guidance
from morpheus_core.priors.proxy.prior import CurrentRenderCounterpart, ProxyPrior
from ops.engine.guided_task import GuidedTask, RenderedStep, step_output
from ops.engine.loop import BadStep, LoopConfig, LoopResult, StepOutput, run_loop
from ops.engine.progress import ProgressFn
from ops.engine.stage_job import StageJob, StageResult, loop_notes


def _concat(values: list[Any]) -> Any:
    first = values[0]
    if isinstance(first, Tensor):
        return torch.cat(values)
    if isinstance(first, tuple):
        return tuple(v for value in values for v in value)
    if dataclasses.is_dataclass(first):
        return type(first)(**{f.name: _concat([getattr(v, f.name) for v in values])
                              for f in dataclasses.fields(first)})
    if all(v == first for v in values):
        return first
    raise TypeError(f"cannot batch condition values {values!r}")


def _same_prior(a: Any, b: Any) -> bool:
    # Real priors are shared by all objects (ModelCache); proxies and their VSD counterpart are per
    # object but behave alike when their corruption is the same (targets come with the condition).
    return a is b or (type(a) is type(b) and isinstance(a, ProxyPrior | CurrentRenderCounterpart)
                      and getattr(a, "corruption", None) == getattr(b, "corruption", None))


def merge_bindings(per_object: Sequence[Mapping[str, PriorBinding]]) -> dict[str, PriorBinding]:
    """One binding per role for object-major concatenated rows: conditions are concatenated field
    by field; the priors and VSD counterparts must be the same for every object."""
    merged = {}
    for role, first in per_object[0].items():
        binds = [b[role] for b in per_object]
        if not all(_same_prior(b.prior, first.prior) and _same_prior(b.finetuned, first.finetuned) for b in binds):
            raise ValueError(f"objects in one batch must share the {role!r} prior and its VSD counterpart")
        merged[role] = PriorBinding(first.prior, first.finetuned, _concat([b.condition for b in binds]))
    return merged


class BatchTask:
    """A ``StageTask`` over one stage's tasks for several objects (see the module docstring)."""

    def __init__(self, tasks: Sequence[GuidedTask], generators: Sequence[torch.Generator]) -> None:
        if not tasks or len(tasks) != len(generators):
            raise ValueError("a batch needs one generator per task and at least one task")
        if any(t.guidance != tasks[0].guidance for t in tasks):
            raise ValueError("objects in one batch must share the stage's guidance configuration")
        self.tasks = list(tasks)
        self.generators = list(generators)
        for task in self.tasks:
            task.shared_by = len(self.tasks)
        self.bad_steps = [0] * len(tasks)
        self.stopped: dict[int, int] = {}  # object → the step its scene converged at
        self._live: list[int] = []

    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        return {f"{i}.{name}": opt for i, t in enumerate(self.tasks) for name, opt in t.optimizers().items()}

    def _render_all(self, step: int) -> tuple[list[int], list[RenderedStep]]:
        """Each running object's renders, one by one; an object whose step is bad sits it out."""
        live, rendered = [], []
        for i in (i for i in range(len(self.tasks)) if i not in self.stopped):
            try:
                rendered.append(self.tasks[i].render_step(step, self.generators[i]))
                live.append(i)
            except BadStep:
                self.bad_steps[i] += 1
        if rendered:  # one sync for all objects: which of them rendered something finite
            finite = torch.stack([torch.isfinite(r.novel).all() & torch.isfinite(r.reference).all()
                                  & torch.isfinite(r.extra_loss) for r in rendered]).tolist()
            for i in [i for i, ok in zip(live, finite, strict=True) if not ok]:
                self.bad_steps[i] += 1
            live = [i for i, ok in zip(live, finite, strict=True) if ok]
            rendered = [r for r, ok in zip(rendered, finite, strict=True) if ok]
        return live, rendered

    def step(self, step: int, generator: torch.Generator) -> StepOutput:
        live, rendered = self._render_all(step)
        self._live = live
        if not live:
            raise BadStep("no object in the batch produced a usable step")
        tasks = [self.tasks[i] for i in live]
        bindings = merge_bindings([t.suite.bindings(r.cameras, r.novel) for t, r in zip(tasks, rendered, strict=True)])
        novel = torch.cat([r.novel for r in rendered])
        photos = torch.cat([t.target_at(r.reference.shape[-1]).rgb for t, r in zip(tasks, rendered, strict=True)])
        lead = tasks[0]
        out = hybrid_guidance(lead.guidance, bindings, lead.schedule, novel, step,
                              torch.cat([r.reference for r in rendered]), photos,
                              [self.generators[i] for i in live], objects=len(live))
        extra = torch.stack([r.extra_loss.float() for r in rendered]).sum()
        terms = {f"{i}/{k}": v for i, r in zip(live, rendered, strict=True) for k, v in r.terms.items()}
        return step_output(out, extra, terms, bool(lead.guidance.needs_finetuned))

    def after_step(self, ok: Tensor | bool) -> None:
        for i, task in enumerate(self.tasks):
            task.after_step(ok if i in self._live else False)

    def state(self) -> dict[str, Any]:
        return {"objects": [t.state() for t in self.tasks], "generators": [g.get_state() for g in self.generators],
                "bad_steps": list(self.bad_steps), "stopped": dict(self.stopped)}

    def load_state(self, state: Mapping[str, Any]) -> None:
        if len(state["objects"]) != len(self.tasks):
            raise ValueError(f"checkpoint holds {len(state['objects'])} objects, this batch {len(self.tasks)}")
        for task, s in zip(self.tasks, state["objects"], strict=True):
            task.load_state(s)
        for gen, s in zip(self.generators, state["generators"], strict=True):
            gen.set_state(s)
        # Counts only grow: a resume (fresh zeros) takes the checkpoint's, while the loop's restore of
        # the last good state after bad steps in a row must not forget the steps sat out since.
        self.bad_steps = [max(a, b) for a, b in zip(self.bad_steps, state["bad_steps"], strict=True)]
        # Likewise a converged object stays stopped (at its first stop step) through a restore.
        self.stopped = {int(i): int(s) for i, s in {**state.get("stopped", {}), **self.stopped}.items()}

    def evaluate(self, done: int) -> dict[str, float]:
        return {f"{i}/{k}": v for i, t in enumerate(self.tasks) if i not in self.stopped
                for k, v in t.evaluate(done).items()}

    def stop_early(self, history: list[dict[str, Any]], done: int, config: LoopConfig) -> bool:
        for i in range(len(self.tasks)):
            if i not in self.stopped and self.tasks[i].stop_early(history, done, config, f"{i}/"):
                self.stopped[i] = done
        return len(self.stopped) == len(self.tasks)


_PER_STEP = ("step", "wall_s", "ok")


def object_result(result: LoopResult, index: int, bad_steps: int, stopped_at: int | None = None) -> LoopResult:
    """Object ``index``'s view of a batch's loop result: its own log columns, and the shared ones —
    the loss terms summed over the batch are renamed ``batch_…`` so nobody reads them as this object's."""
    prefix = f"{index}/"
    history = [{**{(k if k in _PER_STEP else f"batch_{k}"): v for k, v in row.items() if "/" not in k},
                **{k[len(prefix):]: v for k, v in row.items() if k.startswith(prefix)}} for row in result.history]
    # Its own count only: the loop's counts the steps no object could take, which this object's
    # count already holds (when it was still running) or which it sat out (once it had stopped).
    guards = dataclasses.replace(result.guards, bad_step=bad_steps)
    out = dataclasses.replace(result, history=history, guards=guards)
    if stopped_at is None:  # the batch stops only once every object has, so this one ran the schedule
        return out
    return dataclasses.replace(out, steps_run=max(0, stopped_at - (result.resumed_from or 0)), stopped_at=stopped_at)


def run_jobs(jobs: Sequence[StageJob], checkpoint_dir: Path | None = None, progress: ProgressFn | None = None,
             seed: int = 0) -> list[StageResult | Exception]:
    """Optimise one stage for several objects together; one result (or the exception that stopped
    writing that object's output) per job. Jobs must share the stage and its loop settings."""
    if len({(j.stage, j.loop) for j in jobs}) != 1:
        raise ValueError("a batch runs one stage with one loop configuration")
    try:
        batch = BatchTask([j.task for j in jobs], [j.generator for j in jobs])
        result = run_loop(batch, jobs[0].loop, torch.Generator().manual_seed(seed), jobs[0].stage, checkpoint_dir,
                          progress)
        out: list[StageResult | Exception] = []
        for i, job in enumerate(jobs):
            try:
                own = object_result(result, i, batch.bad_steps[i], batch.stopped.get(i))
                res = job.finish(own)
                res.metrics["batch_size"] = len(jobs)
                res.notes.extend(loop_notes(own, job.loop))
                out.append(res)
            except Exception as exc:  # one object's broken output must not lose the others
                out.append(exc)
        return out
    finally:
        for job in jobs:
            job.close()
