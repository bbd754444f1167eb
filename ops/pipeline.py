"""One photo through every stage, with the store's caching, manifests and checkpoints.

For each stage the fingerprint is (the hashes of its inputs — the photo, or upstream outputs —,
the hash of its config including which priors actually run, its code version). A stage whose
fingerprint matches a finished output is skipped as cached; otherwise it runs in a staging
folder that the store commits atomically with its manifest, resuming from the newest valid
checkpoint of the same fingerprint. A failure stops this photo only, leaving every finished
stage in place for the next run.
"""

from __future__ import annotations

import json
import logging
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from assets_store.hashing import bytes_sha256, config_hash, file_sha256
from assets_store.manifest import Fingerprint, Manifest
from assets_store.store import Store
from ops import dmtet as dmtet_stage
from ops import nerf_fit, texture_refine, uv_bake
from ops.config_tree import to_dict
from ops.optimise import ProgressEvent, ProgressFn
from ops.plan import StagePlan, plan_reference, read_plan
from ops.presets import PipelineConfig
from ops.prior_suite import WEIGHT_FREE, PriorSuite
from ops.reference import prepare_reference
from ops.stage_common import StageResult

log = logging.getLogger("morpheus3d")

STAGES = ("reference", "nerf_fit", "dmtet", "texture_refine", "uv_bake")
REFERENCE_CODE_VERSION = "reference-1"
CODE_VERSIONS = {"reference": REFERENCE_CODE_VERSION, "nerf_fit": nerf_fit.CODE_VERSION,
                 "dmtet": dmtet_stage.CODE_VERSION, "texture_refine": texture_refine.CODE_VERSION,
                 "uv_bake": uv_bake.CODE_VERSION}


@dataclass
class StageOutcome:
    stage: str
    status: str  # "ran" | "resumed" | "cached" | "skipped" | "failed"
    wall_s: float = 0.0
    manifest: Manifest | None = None
    error: str | None = None


@dataclass
class PhotoOutcome:
    photo: Path
    key: str
    stages: list[StageOutcome] = field(default_factory=list)
    error: str | None = None

    @property
    def status(self) -> str:
        if self.error:
            return "failed"
        return "cached" if all(s.status in ("cached", "skipped") for s in self.stages) else "ok"

    @property
    def wall_s(self) -> float:
        return sum(s.wall_s for s in self.stages)

    def metric(self, stage: str, name: str) -> Any:
        for s in self.stages:
            if s.stage == stage and s.manifest is not None:
                return s.manifest.metrics.get(name)
        return None


def _output_digest(manifest: Manifest) -> str:
    """One hash for a stage's whole output (every file's content hash)."""
    return bytes_sha256(repr(sorted((k, v.sha256) for k, v in manifest.outputs.items())).encode())


class PhotoRun:
    """The state of one photo's run: where things are, what upstream produced, how to report."""

    def __init__(self, photo: Path, key: str, store: Store, cfg: PipelineConfig, preset: str,
                 init_mesh: Path | None, progress: ProgressFn | None,
                 suites: dict[str, Callable[[], PriorSuite]] | None) -> None:
        self.photo, self.key, self.store, self.cfg, self.preset = photo, key, store, cfg, preset
        self.init_mesh = init_mesh
        self.progress = progress
        self.suites = suites or {}
        self.done: dict[str, Manifest] = {}
        self._plan: StagePlan | None = None
        self.outcome = PhotoOutcome(photo, key)

    def dir(self, stage: str) -> Path:
        return self.store.stage_dir(self.key, stage)

    @property
    def plan(self) -> StagePlan | None:
        """The reference stage's plan, read once (after the reference stage is done)."""
        if self._plan is None:
            self._plan = read_plan(self.dir("reference"))
        return self._plan

    def prior_kind(self, roles: tuple[str, ...]) -> str:
        return "injected" if self.suites else self.cfg.priors.resolve(roles)

    def run_stage(self, stage: str, config: dict[str, Any], inputs: dict[str, str],
                  body: Callable[[Path, Path | None], StageResult]) -> Manifest:
        plain = json.loads(json.dumps(to_dict(config), default=str))
        fp = Fingerprint(inputs=inputs, config_hash=config_hash(plain), code_version=CODE_VERSIONS[stage])
        cached = self.store.lookup(self.key, stage, fp)
        if cached is not None:
            self.outcome.stages.append(StageOutcome(stage, "cached", 0.0, cached))
            self._report(stage, "cached")
            self.done[stage] = cached
            return cached
        ckpt_root = self.store.checkpoint_dir(self.key, stage)
        ckpt = ckpt_root / fp.config_hash[:12] / bytes_sha256(repr(sorted(inputs.items())).encode())[:12]
        resumed = ckpt.is_dir() and any(ckpt.iterdir())
        start = time.perf_counter()
        with self.store.stage_writer(self.key, stage) as writer:
            result = body(writer.path, ckpt)
            wall = time.perf_counter() - start
            plan = self.plan if stage != "reference" else read_plan(writer.path)
            manifest = Manifest(
                stage=stage, photo_key=self.key, fingerprint=fp, outputs={}, config=plain,
                metrics=result.metrics, wall_time_s=round(wall, 3), device=result.device, preset=self.preset,
                plan={} if plan is None else {"refine": plan.highpass_refinement.action,
                                              "grid": plan.dmtet_grid.value, "export_faces": plan.export.value,
                                              "summary": plan.summary()},
                prior=result.prior, notes=tuple(result.notes),
                created_at=datetime.now(timezone.utc).isoformat(timespec="seconds"),
            )
            manifest = writer.commit(manifest)
        self.store.clear_checkpoints(self.key, stage)
        status = "resumed" if resumed else "ran"
        if result.metrics.get("skipped"):
            status = "skipped"
        self.outcome.stages.append(StageOutcome(stage, status, wall, manifest))
        self._report(stage, status)
        self.done[stage] = manifest
        return manifest

    def _report(self, stage: str, status: str) -> None:
        if self.progress is not None:
            self.progress(ProgressEvent(f"{self.key}:{stage}:{status}", 1, 1, 0.0, {}))

    def _progress(self) -> ProgressFn | None:
        if self.progress is None:
            return None
        key, report = self.key, self.progress
        return lambda e: report(ProgressEvent(f"{key}:{e.stage}", e.step, e.total, e.elapsed_s, e.metrics))

    def _suite(self, stage: str) -> PriorSuite | None:
        factory = self.suites.get(stage)
        return factory() if factory is not None else None

    # -- the stages ---------------------------------------------------------------------------

    def reference(self) -> Manifest:
        cfg = self.cfg

        def body(out: Path, _ckpt: Path | None) -> StageResult:
            info = prepare_reference(self.photo, out, cfg.prepare)
            plan = plan_reference(out, cfg.plan)
            return StageResult({"method": info.method, "area_fraction": round(info.area_fraction, 4),
                                "warnings": len(info.warnings), "plan": plan.summary()},
                               "none (segmentation)", "cpu", list(info.warnings))

        config = {"prepare": cfg.prepare, "plan": cfg.plan}
        return self.run_stage("reference", config, {"photo": file_sha256(self.photo)}, body)

    def nerf(self) -> Manifest:
        cfg = self.cfg
        config = {"nerf": cfg.nerf, "priors": cfg.priors, "prior_kind": self.prior_kind(cfg.nerf.guidance.roles),
                  "seed": cfg.seed}

        def body(out: Path, ckpt: Path | None) -> StageResult:
            return nerf_fit.fit_nerf(self.dir("reference"), out, cfg.nerf, cfg.priors, self.key, cfg.device,
                                     cfg.seed, ckpt, self._progress(), self._suite("nerf_fit"))

        return self.run_stage("nerf_fit", config, {"reference": _output_digest(self.done["reference"])}, body)

    def dmtet(self) -> Manifest:
        cfg = self.cfg
        plan = self.plan
        grid = plan.dmtet_grid.value if plan is not None else None
        config = {"dmtet": cfg.dmtet, "priors": cfg.priors, "prior_kind": self.prior_kind(cfg.dmtet.guidance.roles),
                  "seed": cfg.seed, "planned_grid": grid}
        inputs = {"reference": _output_digest(self.done["reference"])}
        if self.init_mesh is not None:
            inputs["init_mesh"] = file_sha256(self.init_mesh)
        else:
            inputs["nerf_fit"] = _output_digest(self.done["nerf_fit"])

        def body(out: Path, ckpt: Path | None) -> StageResult:
            nerf_dir = None if self.init_mesh is not None else self.dir("nerf_fit")
            return dmtet_stage.fit_dmtet(self.dir("reference"), out, cfg.dmtet, cfg.priors, self.key, nerf_dir,
                                         self.init_mesh, grid, cfg.device, cfg.seed, ckpt, self._progress(),
                                         self._suite("dmtet"))

        return self.run_stage("dmtet", config, inputs, body)

    def texture(self) -> Manifest:
        cfg = self.cfg
        plan = self.plan
        refine = plan is None or plan.highpass_refinement.action != "skip"
        reason = "" if plan is None else plan.highpass_refinement.reason
        config = {"texture": cfg.texture, "priors": cfg.priors, "seed": cfg.seed, "planned_refine": refine,
                  "prior_kind": self.prior_kind(cfg.texture.guidance.roles)}
        inputs = {"reference": _output_digest(self.done["reference"]), "dmtet": _output_digest(self.done["dmtet"])}

        def body(out: Path, ckpt: Path | None) -> StageResult:
            return texture_refine.refine_texture(self.dir("reference"), self.dir("dmtet"), out, cfg.texture,
                                                 cfg.priors, self.key, refine, reason, cfg.device, cfg.seed, ckpt,
                                                 self._progress(), self._suite("texture_refine"))

        return self.run_stage("texture_refine", config, inputs, body)

    def bake(self) -> Manifest:
        cfg = self.cfg
        plan = self.plan
        faces = plan.export.value if plan is not None else None
        inputs = {k: _output_digest(self.done[k]) for k in ("reference", "dmtet", "texture_refine")}

        def body(out: Path, _ckpt: Path | None) -> StageResult:
            return uv_bake.bake_asset(self.dir("reference"), self.dir("dmtet"), self.dir("texture_refine"), out,
                                      cfg.bake, faces, cfg.device)

        return self.run_stage("uv_bake", {"bake": cfg.bake, "planned_faces": faces}, inputs, body)


def run_photo(photo: Path, store: Store, cfg: PipelineConfig, preset: str, key: str,
              init_mesh: Path | None = None, progress: ProgressFn | None = None,
              suites: dict[str, Callable[[], PriorSuite]] | None = None, until: str = "uv_bake") -> PhotoOutcome:
    """Every stage for one photo, up to and including ``until``; never raises for a failing photo
    (the outcome says why)."""
    if until not in STAGES:
        raise ValueError(f"until must be one of {STAGES}, got {until!r}")
    run = PhotoRun(Path(photo), key, store, cfg, preset, init_mesh, progress, suites)
    store.cleanup_staging(key)
    named = {"reference": run.reference, "nerf_fit": run.nerf, "dmtet": run.dmtet, "texture_refine": run.texture,
             "uv_bake": run.bake}
    wanted = STAGES[:STAGES.index(until) + 1]
    steps = [named[s] for s in wanted if not (s == "nerf_fit" and init_mesh is not None)]
    for step in steps:
        try:
            step()
        except Exception as exc:
            stage = step.__name__
            log.error("%s: stage %s failed: %s", key, stage, exc)
            log.debug("%s", traceback.format_exc())
            run.outcome.error = f"{stage}: {type(exc).__name__}: {exc}"
            run.outcome.stages.append(StageOutcome(stage, "failed", 0.0, None, str(exc)))
            break
    return run.outcome


def uses_weight_free(outcome: PhotoOutcome) -> bool:
    return any(s.manifest is not None and s.manifest.prior.startswith(WEIGHT_FREE) for s in outcome.stages)
