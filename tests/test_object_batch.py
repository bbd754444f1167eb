"""Several photos optimised together (``ops.engine.batch``): per-object guidance, outputs equal to
one-by-one runs, resume of a killed batch, a failing photo isolated, the CLI's ``--batch``."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from assets_store.runlog import read_runlog
from assets_store.store import Store
from morpheus_core.guidance.diffusion import NoiseSchedule
from morpheus_core.guidance.frequency import BandMask
from morpheus_core.guidance.hybrid import BandWeight, GuidanceConfig, PriorBinding, PriorTerm, hybrid_guidance
from ops.cli import main
from ops.engine import batch as object_batch
from ops.engine.progress import ProgressEvent
from ops.pipeline.runner import Pipeline, stages_until
from ops.stages import dmtet as dmtet_stage
from orchestration.settings import OrchestrationSettings
from tests.helpers import PooledPrior, RandomPrior, TinyFinetunedPrior
from tests.pipeline_helpers import PHOTOS, cli_overrides, manifest, output_hashes, tiny_config

CFG = tiny_config()
KEYS = ("mug.jpg", "box.jpg", "bottle.jpg")
OPTIMISING = ("nerf", "dmtet", "texture")


def _photos(keys: tuple[str, ...] = KEYS) -> list[tuple[Path, str]]:
    return [(PHOTOS / k, k) for k in keys]


@pytest.fixture(scope="module")
def single(tmp_path_factory: pytest.TempPathFactory) -> Store:
    store = Store(tmp_path_factory.mktemp("single"))
    for photo, key in _photos():
        out = Pipeline(store, CFG, "tiny").run([(photo, key)], stages_until("texture"))[0]
        assert out.error is None, out.error
    return store


@pytest.fixture(scope="module")
def batched(tmp_path_factory: pytest.TempPathFactory) -> Store:
    store = Store(tmp_path_factory.mktemp("batched"))
    outcomes = Pipeline(store, CFG, "tiny").run(_photos(), stages_until("texture"))
    assert [o.error for o in outcomes] == [None] * len(KEYS)
    assert all(s.status == "ran" for o in outcomes for s in o.stages)
    return store


def _copy_stages(src: Store, dst: Store, stages: tuple[str, ...]) -> None:
    for key in KEYS:
        for stage in stages:
            shutil.copytree(src.stage_dir(key, stage), dst.stage_dir(key, stage))


def test_a_batch_gives_the_outputs_of_one_by_one_runs(single: Store, batched: Store) -> None:
    for stage in OPTIMISING:
        for key in KEYS:
            assert output_hashes(batched, key, stage) == output_hashes(single, key, stage), (stage, key)
            assert manifest(batched, key, stage).metrics["batch_size"] == len(KEYS)
            assert manifest(single, key, stage).metrics["batch_size"] == 1
    # The runs optimised something: photos differ, so identical outputs are not a constant.
    assert output_hashes(batched, "mug.jpg", "nerf") != output_hashes(batched, "box.jpg", "nerf")
    # Each photo's run log: its own reference PSNR curve, equal to its single run's; the batch's
    # summed loss terms are labelled as such.
    for key in KEYS:
        alone = read_runlog(single.stage_dir(key, "dmtet") / "runlog.parquet")
        together = read_runlog(batched.stage_dir(key, "dmtet") / "runlog.parquet")
        assert [r["ref_psnr"] for r in together] == [r["ref_psnr"] for r in alone]
        assert "batch_loss" in together[-1] and "loss" not in together[-1] and "mask_bce" in together[-1]


def _guidance_case() -> tuple[GuidanceConfig, dict[str, PriorBinding]]:
    """A latent SDS prior with two bands and a pixel VSD prior with a trainable counterpart."""
    c, h, w = 3, 8, 6
    config = GuidanceConfig((
        PriorTerm("3d", "sds", (BandWeight(BandMask.low_pass(0.5), 1.0), BandWeight(BandMask.high_pass(0.5), 0.5)),
                  cfg_scale=3.0),
        PriorTerm("2d", "vsd", (BandWeight(BandMask.high_pass(0.6), 2.0),), cfg_scale=2.0),
    ), lambda_c=0.3, sigma=1.5)
    bindings = {"3d": PriorBinding(PooledPrior((c, h // 2, w // 2), seed=1)),
                "2d": PriorBinding(RandomPrior((c, h, w), seed=2), TinyFinetunedPrior(c, seed=3))}
    return config, bindings


def test_guidance_over_objects_gives_each_object_its_own_gradient() -> None:
    config, bindings = _guidance_case()
    views, schedule, step = 2, NoiseSchedule(), 3
    g = torch.Generator().manual_seed(11)
    novel = [torch.rand(views, 3, 8, 6, generator=g, dtype=torch.float64) for _ in range(2)]
    ref_render = [torch.rand(1, 3, 8, 6, generator=g, dtype=torch.float64) for _ in range(2)]
    photo = [torch.rand(1, 3, 8, 6, generator=g, dtype=torch.float64) for _ in range(2)]
    seeds = (5, 6)

    alone = []
    for i in range(2):
        x, r = novel[i].clone().requires_grad_(True), ref_render[i].clone().requires_grad_(True)
        out = hybrid_guidance(config, bindings, schedule, x, step, r, photo[i], torch.Generator().manual_seed(seeds[i]))
        out.loss.backward()
        alone.append((x.grad, r.grad, out.finetune_loss.detach()))

    x, r = torch.cat(novel).requires_grad_(True), torch.cat(ref_render).requires_grad_(True)
    out = hybrid_guidance(config, bindings, schedule, x, step, r, torch.cat(photo),
                          [torch.Generator().manual_seed(s) for s in seeds], objects=2)
    out.loss.backward()
    for i in range(2):
        torch.testing.assert_close(x.grad[i * views:(i + 1) * views], alone[i][0], rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(r.grad[i:i + 1], alone[i][1], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(out.finetune_loss.detach(), alone[0][2] + alone[1][2], rtol=1e-12, atol=0)
    assert alone[0][2] != alone[1][2] and not torch.equal(alone[0][0], alone[1][0])  # objects really differ

    gens = [torch.Generator().manual_seed(s) for s in seeds]
    with pytest.raises(ValueError, match="generators"):
        hybrid_guidance(config, bindings, schedule, x, step, r, torch.cat(photo), gens[:1], objects=2)
    with pytest.raises(ValueError, match="split evenly"):
        hybrid_guidance(config, bindings, schedule, x[:3], step, generator=gens, objects=2)
    with pytest.raises(ValueError, match="split evenly"):
        hybrid_guidance(config, bindings, schedule, x, step, r[:1], photo[0], gens, objects=2)


class Crash:
    """A machine going away mid-stage: raises from the progress hook once the batch passes a step."""

    def __init__(self, label: str, at_step: int) -> None:
        self.label, self.at_step = label, at_step

    def __call__(self, event: ProgressEvent) -> None:
        if event.stage == self.label and event.step >= self.at_step:
            raise RuntimeError(f"killed at step {event.step}")


def test_a_killed_batch_resumes_when_re_run_with_the_same_photos(single: Store, batched: Store,
                                                                  tmp_path: Path) -> None:
    store = Store(tmp_path / "store")
    _copy_stages(single, store, ("reference",))
    every = CFG.nerf.loop.checkpoint_every
    crashing = Pipeline(store, CFG, "tiny", progress=Crash(f"batch of {len(KEYS)}:nerf", every + 1))
    killed = crashing.run(_photos(), stages_until("nerf"))
    assert all("killed at step" in o.error for o in killed)
    assert all(store.read_manifest(key, "nerf") is None for key in KEYS)
    saved = store.checkpoint_dir(KEYS[0], "nerf").glob("batch-*/step-*.ckpt")
    assert max(int(p.stem.split("-")[1]) for p in saved) == every  # one checkpoint for the whole batch

    again = Pipeline(store, CFG, "tiny").run(_photos(), stages_until("nerf"))
    for key, outcome in zip(KEYS, again, strict=True):
        assert outcome.error is None and outcome.stages[-1].status == "resumed"
        metrics = manifest(store, key, "nerf").metrics
        assert metrics["resumed_from_step"] == every and metrics["steps_run"] == CFG.nerf.loop.steps - every
        assert output_hashes(store, key, "nerf") == output_hashes(batched, key, "nerf"), key
    assert not list(store.checkpoint_dir(KEYS[0], "nerf").glob("**/*.ckpt"))


def test_a_photo_without_a_surface_fails_alone_and_the_others_finish(single: Store, tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Box's DMTet surface is empty from the start: it sits out every step (BadStep for it only),
    fails when writing its output, and the two others get exactly their one-by-one outputs."""
    store = Store(tmp_path / "store")
    _copy_stages(single, store, ("reference", "nerf"))
    real_start, batches = dmtet_stage.start_dmtet, []

    def start(*args, **kwargs) -> object_batch.StageJob:  # type: ignore[no-untyped-def]
        job = real_start(*args, **kwargs)
        if args[4] == "box.jpg":  # object_id: every SDF value outside, so no surface anywhere
            with torch.no_grad():
                job.task.dmtet.sdf.fill_(1.0)
        return job

    class Recorded(object_batch.BatchTask):
        def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
            super().__init__(*args, **kwargs)
            batches.append(self)

    monkeypatch.setattr(dmtet_stage, "start_dmtet", start)
    monkeypatch.setattr(object_batch, "BatchTask", Recorded)
    outcomes = {o.key: o for o in Pipeline(store, CFG, "tiny").run(_photos(), stages_until("dmtet"))}
    assert outcomes["box.jpg"].status == "failed"
    assert outcomes["box.jpg"].error.startswith("dmtet: BadStep") and "no surface" in outcomes["box.jpg"].error
    assert store.read_manifest("box.jpg", "dmtet") is None
    for key in ("mug.jpg", "bottle.jpg"):
        assert outcomes[key].error is None
        assert output_hashes(store, key, "dmtet") == output_hashes(single, key, "dmtet"), key
        assert manifest(store, key, "dmtet").metrics["guard_bad_step"] == 0
    (batch,) = batches
    assert batch.bad_steps == [0, CFG.dmtet.loop.steps, 0]
    # The loop's restore of an older good state (after bad steps in a row) keeps the counts.
    batch.load_state({**batch.state(), "bad_steps": [0, 1, 0]})
    assert batch.bad_steps == [0, CFG.dmtet.loop.steps, 0]


def test_cli_batch_runs_groups_and_rejects_a_zero_batch(single: Store, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "store"
    assert main(["run", str(PHOTOS), "--out", str(out), "--batch", "2", *cli_overrides(CFG)]) == 0
    err = capsys.readouterr().err
    assert "[group 1/2] bottle.jpg, box.jpg" in err and "[group 2/2] mug.jpg" in err
    store = Store(out)
    for key in KEYS:
        assert (store.stage_dir(key, "bake") / "asset.glb").is_file()
        assert output_hashes(store, key, "texture") == output_hashes(single, key, "texture"), key
    assert [manifest(store, k, "nerf").metrics["batch_size"] for k in ("bottle.jpg", "box.jpg", "mug.jpg")] \
        == [2, 2, 1]

    assert main(["run", str(PHOTOS), "--out", str(tmp_path / "none"), "--batch", "0"]) == 2
    assert "--batch must be at least 1" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_batching_photos_together_in_dagster_is_a_setting() -> None:
    assert OrchestrationSettings.from_env({}).batch_together
    assert not OrchestrationSettings.from_env({"MORPHEUS_BATCH_TOGETHER": "0"}).batch_together
    assert OrchestrationSettings.from_env({"MORPHEUS_BATCH_TOGETHER": "true"}).batch_together
    with pytest.raises(ValueError, match="MORPHEUS_BATCH_TOGETHER"):
        OrchestrationSettings.from_env({"MORPHEUS_BATCH_TOGETHER": "sometimes"})
