"""The declaration of a pipeline stage: its id, what it reads and writes, and how it makes its output.

A stage's id is its module name (``ops/stages/<id>.py``), its config key (``--set <id>.…``), its
store folder (``<store>/<photo>/<id>/``) and its Dagster asset key. Each stage module declares one
``Stage``, its QA checks included; ``ops.stages.STAGES`` orders them, and the pipeline, the presets, the
Dagster assets and the QA checks all read that tuple. A stage's ``build`` gets its own config (the ``<id>`` section of
the run's configuration) and the run context (``StageContext``: seed, device, priors, the photo's
folders and upstream outputs), never the whole configuration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeVar

from ops.engine.checks import CheckSpec, CheckThresholds, QACheck
from ops.engine.progress import ProgressFn
from ops.engine.stage_job import StageJob, StageResult

if TYPE_CHECKING:
    from assets_store.manifest import Manifest
    from ops.engine.priors import PriorsConfig, PriorSuite
    from ops.intake.plan import StagePlan


class StageContext(Protocol):
    """What a stage sees of one photo's run when it declares its work (``ops.pipeline.photo_run.PhotoRun``)."""

    key: str
    photo: Path
    init_mesh: Path | None

    @property
    def seed(self) -> int:
        """Seed of the fitting stages' random numbers."""

    @property
    def device(self) -> str:
        """The run's torch device setting (``auto``, ``cpu``, ``cuda:1``…)."""

    @property
    def priors(self) -> PriorsConfig:
        """Which priors guide the optimising stages, and how they run."""

    @property
    def plan(self) -> StagePlan | None: ...

    @property
    def stages(self) -> tuple[str, ...]: ...

    def dir(self, stage: str) -> Path: ...

    def upstream(self, stage: str) -> Manifest: ...

    def photo_hash(self) -> str: ...

    def prior_kind(self, roles: tuple[str, ...]) -> str: ...

    def suite(self, stage: str) -> PriorSuite | None: ...

    def progress(self) -> ProgressFn | None: ...

    def stage_checks(self, stage: str, thresholds: CheckThresholds) -> list[QACheck]:
        """The checks ``stage`` declares, judged from its finished output's metrics (what ``qa`` gathers)."""


@dataclass(frozen=True)
class StageWork:
    """One photo's output of a stage: what decides it and how to make it.

    ``config`` is hashed into the fingerprint and recorded in the manifest; ``inputs`` are content
    hashes beyond the upstream stages' outputs (the photo, an ``--init-mesh`` file); ``body`` makes
    the output in a staging folder (given the checkpoint folder); ``start`` (optimising stages that
    will optimise) sets the job up writing into a folder, so several photos can run it together."""

    config: dict[str, Any]
    body: Callable[[Path, Path | None], StageResult]
    start: Callable[[Path], StageJob] | None = None
    inputs: dict[str, str] = field(default_factory=dict)


def optimising(config: dict[str, Any], start: Callable[[Path], StageJob], ctx: StageContext,
               inputs: dict[str, str] | None = None) -> StageWork:
    """The work of a stage that runs the optimisation loop: alone, or batched through ``start``."""
    return StageWork(config, lambda out, ckpt: start(out).run(ckpt, ctx.progress()), start, inputs or {})


C = TypeVar("C")


@dataclass(frozen=True)
class Stage(Generic[C]):
    """One stage of the pipeline (see the module docstring for what ``id`` names).

    ``reads``: the stages whose outputs are its inputs (those of them this photo runs);
    ``writes``: the files of its output; ``preview``: the one people look at (Dagster UI);
    ``gpu``: it optimises on the GPU (the Dagster GPU pool, batched with other photos); ``cpu_only``: it
    never touches the torch device, so a run of it alone takes no GPU lease; ``replaced_by_init_mesh``:
    ``--init-mesh`` skips it."""

    id: str
    code_version: str
    reads: tuple[str, ...]
    writes: tuple[str, ...]
    preview: str
    gpu: bool
    description: str
    build: Callable[[StageContext, C], StageWork]
    """The stage's work for one photo, from the run context and the stage's own config."""
    config: type[C]
    """Its config class: the ``<id>`` section of the run's configuration (``--set <id>.…``), its defaults
    the stage's own (a preset may set others)."""
    replaced_by_init_mesh: bool = False
    cpu_only: bool = False
    checks: tuple[CheckSpec, ...] = ()
    """The QA checks of its output (the Dagster asset checks, the ``qa`` stage's report)."""
    judge: Callable[[dict[str, Any], CheckThresholds], list[QACheck]] | None = None
    """The outcome of ``checks`` from its manifest metrics (None: it judges its own output, as ``qa`` does)."""
