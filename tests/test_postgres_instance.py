"""The Dagster instance on a real PostgreSQL server: concurrent runs of a backfill, one run killed
mid-stage and re-executed from failure, and nothing lost or duplicated (materialisations, check
results, catalog rows)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from collections import Counter
from pathlib import Path

import dagster as dg
import pytest
import yaml

from ops.stages import STAGE_IDS
from tests.orchestration_helpers import TINY
from tests.pipeline_helpers import PHOTOS as EXAMPLES
from tests.postgres_server import INSTALL_HINT, postgres_server, server_bin

ROOT = Path(__file__).resolve().parent.parent
PHOTOS = ("mug.jpg", "box.jpg", "bottle.jpg")
pytestmark = pytest.mark.skipif(server_bin() is None, reason=f"no PostgreSQL server: {INSTALL_HINT}")


def test_the_postgres_instance_matches_the_sqlite_one_outside_storage() -> None:
    sqlite = yaml.safe_load((ROOT / "dagster_home" / "dagster.yaml").read_text())
    pg = yaml.safe_load((ROOT / "dagster_home_postgres" / "dagster.yaml").read_text())
    assert set(pg.pop("storage")["postgres"]["postgres_db"]) == {"hostname", "port", "username", "password",
                                                                 "db_name"}
    assert pg == sqlite


def _cli(env: dict[str, str], *args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "orchestration.cli", *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


@pytest.mark.timeout(900)
def test_concurrent_backfill_kill_and_reexecute_on_postgres(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with postgres_server() as pg:
        home = tmp_path / "home"
        home.mkdir()
        shutil.copy(ROOT / "dagster_home_postgres" / "dagster.yaml", home / "dagster.yaml")
        photos = tmp_path / "photos"
        photos.mkdir()
        for name in PHOTOS:
            shutil.copy(EXAMPLES / name, photos / name)
        store = tmp_path / "store"
        env = {**os.environ, **pg, "DAGSTER_HOME": str(home), "MORPHEUS_PHOTO_DIR": str(photos),
               "MORPHEUS_STORE": str(store), "MORPHEUS_SET": ";".join(TINY), "MORPHEUS_RETRIES": "0",
               "OMP_NUM_THREADS": "1"}
        # The mug's NeRF stage is long enough to be killed in, with a checkpoint every 2 steps.
        mug_env = {**env, "MORPHEUS_SET": ";".join([*TINY, "nerf.loop.steps=60", "nerf.loop.checkpoint_every=2"])}
        added = _cli(env, "add-photos")
        assert added.wait(timeout=300) == 0, added.stdout.read()

        runs = {name: _cli(mug_env if name == "mug.jpg" else env, "materialize", name) for name in PHOTOS}
        try:
            # The instance calls below run in this process (no start-up of their own) under mug's environment.
            for name, value in mug_env.items():
                monkeypatch.setenv(name, value)
            _kill_and_reexecute(store, runs)
        finally:
            for proc in runs.values():
                proc.kill()
        counts = _read_back()
    print(counts)
    runs_by_status = counts.pop("runs")
    assert runs_by_status == {"SUCCESS": 3, "FAILURE": 1}  # two runs, the killed one, its re-execution
    assert counts.pop("nerf_resumed_from") > 0  # the re-execution resumed from the killed run's checkpoint
    catalog = counts.pop("catalog")
    assert catalog == {name: 1 for name in PHOTOS}
    materialised, checked = counts.pop("materialisations"), counts.pop("checks")
    assets = {a for a, _ in materialised}
    assert assets == set(STAGE_IDS) and all(materialised[(a, p)] == 1 for a in assets for p in PHOTOS), materialised
    assert checked and set(checked.values()) == {1}, checked


def _kill_and_reexecute(store: Path, runs: dict[str, subprocess.Popen[str]]) -> None:
    """Kill mug's run mid-NeRF, let the others finish, re-execute mug's run from failure."""
    ckpts = store / "mug.jpg" / ".checkpoints" / "nerf"
    deadline = time.monotonic() + 300
    while not list(ckpts.glob("**/*.ckpt")):
        if runs["mug.jpg"].poll() is not None or time.monotonic() > deadline:
            pytest.fail(f"mug ended before the kill: {runs['mug.jpg'].communicate()[0][-3000:]}")
        time.sleep(0.05)
    runs["mug.jpg"].send_signal(signal.SIGKILL)  # mid-stage, as a node loss would
    runs["mug.jpg"].wait(timeout=60)
    # What the daemon does for a run whose process died: run monitoring marks it failed, and
    # free_slots_after_run_end_seconds (dagster.yaml) frees the gpu pool slot its NeRF step held,
    # for which the other runs wait.
    _python("""
        from dagster._core.storage.dagster_run import DagsterRunStatus, RunsFilter
        killed = [r for r in instance.get_runs(RunsFilter(tags={"dagster/partition": "mug.jpg"}))
                  if r.status == DagsterRunStatus.STARTED]
        assert len(killed) == 1, killed
        instance.report_run_failed(killed[0])
        instance.event_log_storage.free_concurrency_slots_for_run(killed[0].run_id)
    """)
    for name in ("box.jpg", "bottle.jpg"):
        out, _ = runs[name].communicate(timeout=500)
        assert runs[name].returncode == 0, out[-3000:]
    _python("""
        from dagster._core.storage.dagster_run import DagsterRunStatus, RunsFilter
        from tests.orchestration_helpers import job_from_env
        (failed,) = instance.get_runs(RunsFilter(tags={"dagster/partition": "mug.jpg"},
                                                 statuses=[DagsterRunStatus.FAILURE]))
        options = dg.ReexecutionOptions.from_failure(failed.run_id, instance)
        # The partition tag is not carried over by itself: a partitioned re-execution names it again.
        result = dg.execute_job(dg.reconstructable(job_from_env), instance, reexecution_options=options,
                                tags={"dagster/partition": "mug.jpg"})
        assert result.success
    """)


def _python(body: str) -> str:
    """``body`` run here with ``instance`` (the Postgres-backed instance of ``DAGSTER_HOME``) open; its stdout.
    In this process, not a fresh one: the instance holds everything the runs left, and a re-execution from
    failure loads its job by name (``dg.reconstructable``) wherever it runs."""
    from dagster._core.storage.defs_state.base import set_defs_state_storage

    out = io.StringIO()
    with dg.DagsterInstance.get() as instance, set_defs_state_storage(instance.defs_state_storage), \
            contextlib.redirect_stdout(out):
        exec(textwrap.dedent(body), {"dg": dg, "instance": instance})
    return out.getvalue()


def _read_back() -> dict:
    """What the instance and the catalog hold afterwards, read back from the instance's database."""
    out = _python("""
        import json, os
        from collections import Counter
        from dagster import DagsterEventType, EventRecordsFilter
        from assets_store.catalog import Catalog
        from assets_store.store import Store
        runs = Counter(r.status.value for r in instance.get_runs())
        mats, checks, resumed = Counter(), Counter(), None
        for key in instance.get_asset_keys():
            for rec in instance.fetch_materializations(key, limit=1000).records:
                m = rec.asset_materialization
                mats[f"{key.to_user_string()}|{m.partition}"] += 1
                if key.to_user_string() == "nerf" and m.partition == "mug.jpg":
                    resumed = m.metadata["resumed_from_step"].value
        for rec in instance.get_event_records(EventRecordsFilter(DagsterEventType.ASSET_CHECK_EVALUATION),
                                              limit=10000):
            e = rec.event_log_entry.dagster_event.event_specific_data
            checks[f"{e.asset_key.to_user_string()}.{e.check_name}|{e.partition}"] += 1
        rows = Catalog(Store(os.environ["MORPHEUS_STORE"]).catalog_dir).read().to_pylist()
        print(json.dumps({"runs": runs, "materialisations": mats, "checks": checks, "nerf_resumed_from": resumed,
                          "catalog": Counter(r["photo_key"] for r in rows)}))
    """)
    data = json.loads(out.strip().splitlines()[-1])
    data["materialisations"] = Counter({tuple(k.split("|")): v for k, v in data["materialisations"].items()})
    data["checks"] = Counter({tuple(k.split("|")): v for k, v in data["checks"].items()})
    return data
