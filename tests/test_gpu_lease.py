"""GPU leases: which GPUs, processes never sharing one (or sharing it by slots, never more), a
killed holder freeing its GPU at once, a waiting run saying so; the gpu pool's limit; staging
liveness by lock instead of process id."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from assets_store.store import Store
from ops.engine.gpu_lease import GpuLeaseError, LeaseSettings, gpu_lease, leased_device, visible_gpus

ROOT = Path(__file__).resolve().parent.parent


def test_which_gpus() -> None:
    assert visible_gpus({"MORPHEUS_GPUS": "3,1", "CUDA_VISIBLE_DEVICES": "1,3,5"}) == [("3", "cuda:1"),
                                                                                        ("1", "cuda:0")]
    assert visible_gpus({"CUDA_VISIBLE_DEVICES": "4,6"}) == [("4", "cuda:0"), ("6", "cuda:1")]
    assert visible_gpus({"MORPHEUS_GPUS": "0,2"}) == [("0", "cuda:0"), ("2", "cuda:2")]
    assert visible_gpus({"MORPHEUS_GPUS": "none"}) == [] and visible_gpus({"CUDA_VISIBLE_DEVICES": ""}) == []
    with pytest.raises(GpuLeaseError, match="hides"):
        visible_gpus({"MORPHEUS_GPUS": "2", "CUDA_VISIBLE_DEVICES": "0,1"})
    with pytest.raises(GpuLeaseError, match="twice"):
        visible_gpus({"MORPHEUS_GPUS": "1,1"})


def _worker(folder: Path, gpus: str, body: str, **env: str) -> subprocess.Popen[str]:
    code = textwrap.dedent(f"""
        import json, logging, sys, time
        from pathlib import Path
        logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(message)s")
        from ops.engine.gpu_lease import LeaseSettings, gpu_lease
        settings = LeaseSettings(folder=Path({str(folder)!r}), poll_s=0.02, report_every_s=0.2)
    """) + textwrap.dedent(body)
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, text=True, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env={**os.environ, "MORPHEUS_GPUS": gpus, **env})


def test_competing_processes_never_share_a_gpu(tmp_path: Path) -> None:
    body = """
        for _ in range(4):
            with gpu_lease(settings) as lease:
                start = time.time(); time.sleep(0.15)
                print(json.dumps([lease.gpu, lease.device, start, time.time()]), flush=True)
    """
    procs = [_worker(tmp_path / "leases", "0,1,2", body) for _ in range(7)]
    spans = []
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        spans += [json.loads(line) for line in out.splitlines()]
    assert len(spans) == 28 and {s[0] for s in spans} == {"0", "1", "2"}
    for gpu in "012":
        mine = sorted((s[2], s[3]) for s in spans if s[0] == gpu)
        assert all(a_end <= b_start for (_, a_end), (b_start, _) in itertools.pairwise(mine)), gpu
    assert all(s[1] == f"cuda:{s[0]}" for s in spans)


def _max_overlap(spans: list[tuple[float, float]]) -> int:
    events = sorted([(a, 1) for a, _ in spans] + [(b, -1) for _, b in spans], key=lambda e: (e[0], e[1]))
    return max(itertools.accumulate(d for _, d in events))


def test_slots_let_that_many_processes_share_a_gpu_and_no_more(tmp_path: Path) -> None:
    body = """
        for _ in range(3):
            with gpu_lease(settings) as lease:
                start = time.time(); time.sleep(0.2)
                print(json.dumps([lease.gpu, lease.slot, lease.slots, start, time.time()]), flush=True)
    """
    procs = [_worker(tmp_path / "leases", "0,1", body, MORPHEUS_GPU_SLOTS="2") for _ in range(6)]
    spans = []
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        spans += [json.loads(line) for line in out.splitlines()]
    assert len(spans) == 18 and {(s[0], s[1]) for s in spans} == {("0", 0), ("0", 1), ("1", 0), ("1", 1)}
    assert all(s[2] == 2 for s in spans)
    for gpu in "01":
        assert _max_overlap([(s[3], s[4]) for s in spans if s[0] == gpu]) == 2, gpu  # shared, by two at most
        for slot in (0, 1):
            mine = sorted((s[3], s[4]) for s in spans if s[0] == gpu and s[1] == slot)
            assert all(a_end <= b_start for (_, a_end), (b_start, _) in itertools.pairwise(mine)), (gpu, slot)


def test_runs_spread_over_the_gpus_before_sharing_one(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MORPHEUS_GPUS", "0,1")
    monkeypatch.setenv("MORPHEUS_GPU_SLOTS", "2")
    settings = LeaseSettings(folder=tmp_path / "leases", poll_s=0.02, timeout_s=0.2)
    with gpu_lease(settings) as a, gpu_lease(settings) as b, gpu_lease(settings) as c, gpu_lease(settings) as d:
        assert {a.gpu, b.gpu} == {"0", "1"} and a.slot == b.slot == 0
        assert {c.gpu, d.gpu} == {"0", "1"} and c.slot == d.slot == 1
        assert c.describe().startswith(f"GPU {c.gpu} slot 2 of 2 (cuda:{c.gpu}), leased after waiting")
        assert c.lock_path.name == f"gpu-{c.gpu}.slot1.lock" and a.lock_path.name == f"gpu-{a.gpu}.lock"
        with pytest.raises(GpuLeaseError, match="came free"), gpu_lease(settings):
            pass


@pytest.mark.parametrize("value", ["0", "two", "-1", ""])
def test_a_bad_slot_setting_is_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv("MORPHEUS_GPUS", "0")
    monkeypatch.setenv("MORPHEUS_GPU_SLOTS", value)
    with pytest.raises(GpuLeaseError, match=r"MORPHEUS_GPU_SLOTS.*whole number"), \
            gpu_lease(LeaseSettings(folder=tmp_path / "leases")):
        pass
    assert not (tmp_path / "leases").exists()  # nothing taken, nothing written


def test_running_out_of_memory_names_the_settings_to_lower(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import torch

    monkeypatch.setenv("MORPHEUS_GPUS", "0")
    monkeypatch.setenv("MORPHEUS_LEASE_DIR", str(tmp_path / "leases"))
    for slots, expected in (("3", "MORPHEUS_GPU_SLOTS=3 runs share each GPU"),
                            ("1", "lower the objects per batch (--batch, MORPHEUS_BATCH)")):
        monkeypatch.setenv("MORPHEUS_GPU_SLOTS", slots)
        with pytest.raises(torch.OutOfMemoryError) as caught, leased_device("cuda"):
            raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 384.00 MiB.")
        assert any(expected in note for note in caught.value.__notes__)
    with pytest.raises(ValueError) as other, leased_device("cuda"):
        raise ValueError("a bad setting")
    assert not getattr(other.value, "__notes__", None)  # only memory errors get the hint


def test_a_killed_holder_frees_its_gpu_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MORPHEUS_GPUS", "0")
    settings = LeaseSettings(folder=tmp_path / "leases", poll_s=0.02, timeout_s=0.3)
    holder = _worker(settings.folder, "0", """
        with gpu_lease(settings):
            print("leased", flush=True)
            time.sleep(120)
    """)
    assert holder.stdout.readline().strip() == "leased"
    with pytest.raises(GpuLeaseError, match="came free"), gpu_lease(settings):
        pass
    holder.send_signal(signal.SIGKILL)
    holder.wait(timeout=30)
    start = time.monotonic()
    with gpu_lease(settings) as lease:
        assert lease.gpu == "0" and time.monotonic() - start < 0.3


def test_a_waiting_run_says_that_it_waits(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MORPHEUS_GPUS", "7")
    settings = LeaseSettings(folder=tmp_path / "leases", poll_s=0.02)
    with gpu_lease(settings) as held:
        assert held.device == "cuda:7"
        waiter = _worker(settings.folder, "7", """
            with gpu_lease(settings) as lease:
                print(lease.describe(), flush=True)
        """)
        time.sleep(1.0)
        assert waiter.poll() is None  # still waiting
    out, err = waiter.communicate(timeout=60)
    assert waiter.returncode == 0, err
    assert "waiting" in err and "for a GPU: 7 busy" in err
    assert out.startswith("GPU 7 (cuda:7), leased after waiting") and float(out.split()[-2]) >= 0.5


def test_the_pipeline_device_is_leased_only_for_cuda(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MORPHEUS_GPUS", "0,1")
    monkeypatch.setenv("MORPHEUS_LEASE_DIR", str(tmp_path / "leases"))
    with leased_device("cpu") as (device, lease):
        assert device == "cpu" and lease is None  # a CPU run changes nothing
    with gpu_lease(LeaseSettings(folder=tmp_path / "leases"), want="0"), leased_device("cuda") as (device, lease):
        assert device == "cuda:1" and lease is not None and lease.gpu == "1"
    with leased_device("cuda:9") as (device, lease):
        assert device == "cuda:9" and lease is None  # not visible: the stage fails with torch's reason
    monkeypatch.setenv("MORPHEUS_GPUS", "none")
    with leased_device("cuda") as (device, lease):
        assert device == "cuda" and lease is None


def test_gpu_pool_limit_is_the_gpu_count(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    import dagster as dg

    from orchestration.cli import main

    monkeypatch.setenv("DAGSTER_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("MORPHEUS_PHOTO_DIR", str(ROOT / "examples" / "photos"))
    monkeypatch.setenv("MORPHEUS_STORE", str(tmp_path / "store"))
    monkeypatch.setenv("MORPHEUS_GPUS", "0,1,2")

    def limit() -> int:
        with dg.DagsterInstance.get() as instance:
            return instance.event_log_storage.get_concurrency_info("gpu").slot_count

    assert main(["gpu-pool"]) == 0 and limit() == 3
    monkeypatch.setenv("MORPHEUS_GPUS", "none")
    assert main(["gpu-pool"]) == 0 and limit() == 3  # a limit set before is kept
    assert "keeps its limit 3" in capsys.readouterr().out
    assert main(["gpu-pool", "--force"]) == 0 and limit() == 1  # a CPU host: one at a time
    monkeypatch.setenv("MORPHEUS_GPUS", "0,1,2")
    monkeypatch.setenv("MORPHEUS_GPU_SLOTS", "2")
    assert main(["gpu-pool", "--force"]) == 0 and limit() == 6  # every slot of every GPU
    assert "3 GPU(s) found" in capsys.readouterr().out


def test_registering_photos_sets_the_gpu_pool_before_any_run_claims_it(tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """A pool left to dagster.yaml's default is created by the first step that claims it, which races
    between concurrent runs on Postgres (Dagster issue 33552): ``add-photos`` sets it first, keeping
    a limit set before, and leaves stdout to the keys."""
    import dagster as dg

    from orchestration.cli import main

    monkeypatch.setenv("DAGSTER_HOME", str(tmp_path / "home"))
    monkeypatch.setenv("MORPHEUS_PHOTO_DIR", str(ROOT / "examples" / "photos"))
    monkeypatch.setenv("MORPHEUS_STORE", str(tmp_path / "store"))
    monkeypatch.setenv("MORPHEUS_GPUS", "0,1")

    def keys_and_limit() -> tuple[set[str], int | None]:
        with dg.DagsterInstance.get() as instance:
            storage = instance.event_log_storage
            keys = set(storage.get_concurrency_keys())
            return keys, storage.get_concurrency_info("gpu").slot_count if "gpu" in keys else None

    (tmp_path / "home").mkdir()
    assert keys_and_limit() == (set(), None)
    assert main(["add-photos", "mug.jpg"]) == 0
    out = capsys.readouterr()
    assert out.out.strip() == "mug.jpg" and "limit 2" in out.err
    assert keys_and_limit() == ({"gpu"}, 2)
    monkeypatch.setenv("MORPHEUS_GPUS", "none")
    assert main(["add-photos", "box.jpg"]) == 0 and keys_and_limit() == ({"gpu"}, 2)


def test_a_live_writer_on_another_host_keeps_its_staging_folder(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    store = Store(tmp_path / "store")
    # The folder's name carries a process id that does not exist here, as a writer on another host would.
    monkeypatch.setattr("assets_store.store.os.getpid", lambda: 999_999_999)
    with store.stage_writer("photo.jpg", "reference") as writer:
        (writer.path / "half.bin").write_bytes(os.urandom(64))
        assert store.cleanup_staging("photo.jpg") == [] and writer.path.is_dir()
    assert not store.staging_root("photo.jpg").exists() or not any(store.staging_root("photo.jpg").iterdir())


def test_a_killed_writer_is_cleaned_up_at_once(tmp_path: Path) -> None:
    store_root = tmp_path / "store"
    code = textwrap.dedent(f"""
        import time
        from assets_store.store import Store
        with Store({str(store_root)!r}).stage_writer("photo.jpg", "nerf") as w:
            (w.path / "partial.bin").write_bytes(b"x" * 100)
            print(w.path, flush=True)
            time.sleep(120)
    """)
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, text=True, stdout=subprocess.PIPE)
    folder = Path(proc.stdout.readline().strip())
    store = Store(store_root)
    assert store.cleanup_staging("photo.jpg") == [] and folder.is_dir()  # alive: kept
    proc.kill()
    proc.wait(timeout=30)
    assert store.cleanup_staging("photo.jpg") == [folder] and not folder.exists()
    assert not list(store_root.glob("photo.jpg/.staging/*"))  # its lock file went with it


def test_a_staging_folder_without_a_lock_is_judged_by_age_not_by_process_id(tmp_path: Path) -> None:
    store = Store(tmp_path / "store")
    staging = store.staging_root("photo.jpg")
    staging.mkdir(parents=True)
    # From before the writer locks, by a process id that is dead here but may be alive on another host.
    folder = staging / f"nerf.999999999.{os.urandom(8).hex()}"
    folder.mkdir()
    (folder / "half.bin").write_bytes(os.urandom(64))
    assert store.cleanup_staging("photo.jpg") == [] and folder.is_dir()
    old = time.time() - 2 * 24 * 3600
    os.utime(folder, (old, old))
    assert store.cleanup_staging("photo.jpg") == [folder] and not folder.exists()
