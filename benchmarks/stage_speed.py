"""Time per optimisation step of each stage at a preset's sizes, with the weight-free proxy prior.

This isolates the stage loop's own cost (rendering, losses, optimiser, guards) from the priors'
(``benchmarks/prior_speed.py`` measures those): the two add up to a stage's step time. Steps run
on a real prepared reference through the same task classes the stages use; the NeRF trained for
these few steps feeds the DMTet stage, whose mesh feeds the texture stage.

    python benchmarks/stage_speed.py --preset paper --device cuda --steps 40 --tag h200
    python benchmarks/stage_speed.py --preset draft --device cpu --steps 10 --tag cpu
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from collections import Counter
from datetime import date
from pathlib import Path
from typing import Any

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from assets_store.atomic import atomic_write_text
from assets_store.store import Store
from benchmarks.timing import sync_device
from morpheus_core.geometry.tet_surface import DMTet, DMTetConfig
from morpheus_core.texture import TextureField
from ops.config.presets import preset
from ops.engine.artifacts import save_module
from ops.engine.loop import LoopConfig, run_loop
from ops.engine.priors import build_suite
from ops.engine.target import ReferenceTarget
from ops.intake.plan import read_plan
from ops.pipeline.runner import Pipeline
from ops.stages.dmtet import DMTetTask, choose_grid, init_from_nerf
from ops.stages.nerf import NERF_FILE, NerfTask
from ops.stages.texture import TextureTask

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


_OUR_CODE = (f"{os.sep}morpheus_core{os.sep}", f"{os.sep}ops{os.sep}")


class OpCounter(TorchDispatchMode):
    """Counts the aten operators dispatched (backward and optimiser included): on a GPU each is a
    kernel launch or a view, so the count tracks the host work of launch-bound stages on any device.
    Each is charged to the innermost line of our code that issued it, so the sites to work on come out
    ranked. The backward's operators go to the line that called ``backward()`` where the autograd
    engine runs in that thread (CPU), else to "backward" (a device thread has no Python caller)."""

    def __init__(self) -> None:
        super().__init__()
        self.calls = 0
        self.sites: Counter[str] = Counter()

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        self.calls += 1
        frame = sys._getframe(1)
        while frame is not None and not any(part in frame.f_code.co_filename for part in _OUR_CODE):
            frame = frame.f_back
        site = "backward" if frame is None else \
            f"{Path(frame.f_code.co_filename).relative_to(ROOT)}:{frame.f_lineno}"
        self.sites[site] += 1
        return func(*args, **(kwargs or {}))


def ops_per_step(task: object, gen: torch.Generator, sites: int, extra: int = 2) -> dict[str, Any]:
    """Operators of a steady-state step: a loop of 2 + ``extra`` steps minus a loop of 2, over ``extra``.
    Both loops pay the same set-up (the last-good-state copy), the same first two steps (a loop's
    second step still issues extra operators) and one log row at their last step, so those cancel
    and only the steady-state steps in between remain."""
    counters = []
    for steps in (2, 2 + extra):
        with OpCounter() as counter:
            run_loop(task, LoopConfig(steps, log_every=10_000, grad_clip=None), gen, "ops")  # type: ignore[arg-type]
        counters.append(counter)
    short, long = counters
    per_step = long.sites.copy()
    per_step.subtract(short.sites)
    top = [(site, n / extra) for site, n in per_step.most_common(sites) if n > 0]
    return {"aten_ops_per_step": (long.calls - short.calls) / extra, "op_sites": dict(top)}


def _time(task: object, steps: int, warmup: int, dev: torch.device, gen: torch.Generator,
          sites: int = 0) -> dict[str, Any]:
    run_loop(task, LoopConfig(warmup, log_every=10_000, grad_clip=None), gen, "warmup")  # type: ignore[arg-type]
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    sync_device(dev)
    start = time.perf_counter()
    res = run_loop(task, LoopConfig(steps, log_every=10_000, grad_clip=None), gen, "timed")  # type: ignore[arg-type]
    sync_device(dev)
    ms = (time.perf_counter() - start) / steps * 1000
    peak = torch.cuda.max_memory_allocated(dev) / 2**30 if dev.type == "cuda" else float("nan")
    return {"ms_per_step": round(ms, 2), "peak_gib": round(peak, 2), "skipped": res.guards.skipped,
            **ops_per_step(task, gen, sites)}


def measure(preset_name: str, device: str, steps: int, warmup: int, photo: Path, store_root: Path,
            sites: int = 0) -> dict:
    cfg = preset(preset_name, [f"device={device}", "priors.kind=proxy"])
    dev = torch.device(device)
    key = photo.name
    store = Store(store_root)
    outcome = Pipeline(store, cfg, preset_name).run([(photo, key)], ["reference"])[0]
    if outcome.error:
        raise RuntimeError(outcome.error)
    ref_dir = store.stage_dir(key, "reference")
    gen = torch.Generator().manual_seed(0)
    rows = {}

    suite = build_suite(cfg.priors, dev, ref_dir, key, ("3d",))
    nerf = NerfTask(cfg.nerf, ReferenceTarget.load(ref_dir, cfg.nerf.resolution, dev), suite, dev, gen)
    rows["nerf"] = _time(nerf, steps, warmup, dev, gen, sites) | {"resolution": cfg.nerf.resolution,
                                                                "samples": cfg.nerf.render.n_samples}
    work = Path(tempfile.mkdtemp())
    save_module(work / NERF_FILE, nerf.field, cfg.nerf.model, {"occupancy": nerf.occupancy.density})

    plan = read_plan(ref_dir)
    grid = choose_grid(cfg.dmtet, plan.dmtet_grid.value if plan else None)
    dmtet = DMTet(DMTetConfig(resolution=grid, deform_scale=cfg.dmtet.deform_scale), device=dev)
    texture = TextureField(cfg.dmtet.texture_field, generator=gen).to(dev)
    init_from_nerf(dmtet, texture, work, cfg.dmtet, dev, gen)
    dtask = DMTetTask(cfg.dmtet, ReferenceTarget.load(ref_dir, cfg.dmtet.resolution, dev), suite, dmtet, texture, dev)
    faces = dtask.mesh().num_faces
    rows["dmtet"] = _time(dtask, steps, warmup, dev, gen, sites) | {"resolution": cfg.dmtet.resolution, "grid": grid,
                                                             "faces": faces}

    mesh = dtask.mesh()
    mesh = type(mesh)(mesh.vertices.detach(), mesh.faces)
    suite2 = build_suite(cfg.priors, dev, ref_dir, key, cfg.texture.guidance.roles, cfg.texture.guidance.vsd_roles)
    ttask = TextureTask(cfg.texture, ReferenceTarget.load(ref_dir, cfg.texture.resolution, dev), suite2, mesh,
                        texture, dev)
    rows["texture"] = _time(ttask, steps, warmup, dev, gen, sites) | {"resolution": cfg.texture.resolution,
                                                                      "faces": faces}
    schedule = {"nerf": cfg.nerf.loop.steps, "dmtet": cfg.dmtet.loop.steps,
                "texture": cfg.texture.loop.steps}
    for stage, row in rows.items():
        row["schedule_steps"] = schedule[stage]
        row["projected_min"] = round(row["ms_per_step"] * schedule[stage] / 60000, 2)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else platform.processor() or platform.machine()
    return {"date": date.today().isoformat(), "device": name, "torch": torch.__version__, "preset": preset_name,
            "photo": photo.name, "timed_steps": steps, "warmup_steps": warmup, "stages": rows,
            "projected_total_min_without_priors": round(sum(r["projected_min"] for r in rows.values()), 2)}


def to_markdown(res: dict) -> str:
    lines = [f"# Stage step time, `{res['preset']}` preset, proxy prior — {res['device']}, {res['date']}", "",
             f"torch {res['torch']}; {res['timed_steps']} timed steps after {res['warmup_steps']} warm-up, photo "
             f"`{res['photo']}`. The proxy prior's cost is a mesh render of the target; the real priors' cost "
             "is in `prior_speed_*.md` and adds to these.", "",
             "| stage | size | ms/step | aten ops/step | peak GiB | schedule steps | projected min |",
             "|---|---|---|---|---|---|---|"]
    for stage, r in res["stages"].items():
        size = f"{r['resolution']}²" + (f", {r['samples']} spp" if "samples" in r else "") + \
            (f", grid {r['grid']}" if "grid" in r else "") + (f", {r['faces']} faces" if "faces" in r else "")
        lines.append(f"| {stage} | {size} | {r['ms_per_step']} | {r.get('aten_ops_per_step', '–')} | {r['peak_gib']} | "
                     f"{r['schedule_steps']} | {r['projected_min']} |")
    lines += ["", f"Projected whole schedule without the priors: **{res['projected_total_min_without_priors']} min**."]
    for stage, r in res["stages"].items():
        if r.get("op_sites"):
            lines += ["", f"aten operators per {stage} step by the line of our code that issued them:", "",
                      "| ops | site |", "|---:|---|"]
            lines += [f"| {n} | `{site}` |" for site, n in r["op_sites"].items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="draft")
    p.add_argument("--device", default="cpu")
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--photo", type=Path, default=ROOT / "examples" / "photos" / "mug.jpg")
    p.add_argument("--store", type=Path, help="where the reference is prepared (default: a temp folder)")
    p.add_argument("--tag", default="cpu")
    p.add_argument("--sites", type=int, default=0, metavar="N",
                   help="list the N lines of our code that issue the most aten operators per step, per stage")
    args = p.parse_args(argv)
    res = measure(args.preset, args.device, args.steps, args.warmup, args.photo,
                  args.store or Path(tempfile.mkdtemp()), args.sites)
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = RESULTS / f"stage_speed_{args.preset}_{args.tag}"
    atomic_write_text(stem.with_suffix(".json"), json.dumps(res, indent=2) + "\n")
    atomic_write_text(stem.with_suffix(".md"), to_markdown(res))
    print(to_markdown(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
