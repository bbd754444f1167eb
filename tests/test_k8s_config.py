"""The Kubernetes deployment files and code location, checked offline (no cluster, no Postgres).

``deploy/k8s/dagster.yaml`` goes through the loader the instance itself uses (instance schema and
the concurrency cross-checks), then each pluggable section through its class's own
``config_type()``, which the instance schema leaves unchecked until the class is built in a pod.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from dagster import DagsterInvalidConfigError
from dagster._config import process_config, resolve_to_config_type
from dagster._core.instance.config import ConcurrencyConfig
from dagster._core.instance.ref import InstanceRef

REPO = Path(__file__).resolve().parents[1]
K8S_DIR = REPO / "deploy" / "k8s"
INSTANCE_YAML = K8S_DIR / "dagster.yaml"
VALUES_YAML = K8S_DIR / "values.yaml"
MODULE = "orchestration.k8s_definitions"
PG_ENV = {
    "DAGSTER_PG_USERNAME": "dagster",
    "DAGSTER_PG_PASSWORD": "secret",
    "DAGSTER_PG_HOST": "postgres.example.internal",
    "DAGSTER_PG_DB": "dagster",
}
SECTIONS = ("run_launcher", "storage", "run_coordinator")
GPU_TAG = "dagster-k8s/config"


@pytest.fixture
def pg_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for key, value in PG_ENV.items():
        monkeypatch.setenv(key, value)


def load_instance_ref(config_dir: Path, base_dir: Path) -> InstanceRef:
    """What the instance does at start-up: ``dagster_instance_config`` validates the file against
    ``dagster_instance_config_schema()`` plus the concurrency rules; the ref maps each section to its class."""
    return InstanceRef.from_dir(str(base_dir), config_dir=str(config_dir))


def section_classes(ref: InstanceRef) -> dict[str, Any]:
    return {
        "run_launcher": ref.run_launcher_data,
        "storage": ref.storage_data,
        "run_coordinator": ref.run_coordinator_data,
    }


def validate_instance_yaml(config_dir: Path, base_dir: Path) -> dict[str, Any]:
    """Validate ``config_dir/dagster.yaml`` completely; returns each section's processed config.

    ``process_config`` resolves ``{env: ...}`` values, so the Postgres env vars must be set.
    Raises ``DagsterInvalidConfigError`` naming the section and the offending key.
    """
    ref = load_instance_ref(config_dir, base_dir)
    processed: dict[str, Any] = {}
    for section, data in section_classes(ref).items():
        cls = getattr(importlib.import_module(data.module_name), data.class_name)
        result = process_config(resolve_to_config_type(cls.config_type()), data.config_dict)
        if not result.success:
            raise DagsterInvalidConfigError(
                f"Errors in {section} ({data.module_name}.{data.class_name}) config of {config_dir / 'dagster.yaml'}.",
                result.errors,
                data.config_dict,
            )
        processed[section] = result.value
    return processed


def instance_yaml() -> dict[str, Any]:
    return yaml.safe_load(INSTANCE_YAML.read_text())


def write_instance(tmp_path: Path, config: dict[str, Any]) -> Path:
    config_dir = tmp_path / "broken"
    config_dir.mkdir()
    (config_dir / "dagster.yaml").write_text(yaml.safe_dump(config))
    return config_dir


# --- deploy/k8s/dagster.yaml ------------------------------------------------------------------


def test_instance_yaml_validates(tmp_path: Path, pg_env: None) -> None:
    processed = validate_instance_yaml(K8S_DIR, tmp_path)

    ref = load_instance_ref(K8S_DIR, tmp_path)
    assert (ref.run_launcher_data.module_name, ref.run_launcher_data.class_name) == ("dagster_k8s", "K8sRunLauncher")
    assert (ref.storage_data.module_name, ref.storage_data.class_name) == ("dagster_postgres", "DagsterPostgresStorage")
    assert ref.run_coordinator_data.class_name == "QueuedRunCoordinator"

    launcher = processed["run_launcher"]
    assert launcher["job_namespace"] and launcher["service_account_name"] and launcher["instance_config_map"]
    assert processed["storage"]["postgres_db"]["hostname"] == PG_ENV["DAGSTER_PG_HOST"]


def test_postgres_credentials_come_from_env() -> None:
    postgres_db = instance_yaml()["storage"]["postgres"]["postgres_db"]
    for key in ("username", "password", "hostname", "db_name"):
        assert set(postgres_db[key]) == {"env"}, f"postgres_db.{key} must be read from an env var"


def test_missing_postgres_env_var_fails(tmp_path: Path, pg_env: None, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DAGSTER_PG_HOST")
    with pytest.raises(DagsterInvalidConfigError, match="DAGSTER_PG_HOST"):
        validate_instance_yaml(K8S_DIR, tmp_path)


def test_effective_run_and_pool_limits(tmp_path: Path) -> None:
    """The limits the daemon will actually use, merged the way the instance merges them."""
    ref = load_instance_ref(K8S_DIR, tmp_path)
    coordinator = ref.run_coordinator_data.rehydrate()  # the one section that builds offline
    concurrency = ConcurrencyConfig.from_concurrency_settings(
        ref.settings.get("concurrency", {}), coordinator.get_run_queue_config()
    )
    raw = instance_yaml()["concurrency"]
    assert concurrency.run_queue_config.max_concurrent_runs == raw["runs"]["max_concurrent_runs"] > 0
    assert concurrency.pool_config.default_pool_limit == raw["pools"]["default_limit"] >= 1


def _misspell_launcher_key(config: dict[str, Any]) -> None:
    launcher = config["run_launcher"]["config"]
    launcher["job_namespce"] = launcher.pop("job_namespace")


def _misspell_postgres_key(config: dict[str, Any]) -> None:
    postgres_db = config["storage"]["postgres"]["postgres_db"]
    postgres_db["db_nam"] = postgres_db.pop("db_name")


def _misspell_coordinator_key(config: dict[str, Any]) -> None:
    coordinator = config["run_coordinator"]["config"]
    coordinator["dequeue_num_worker"] = coordinator.pop("dequeue_num_workers")


def _run_limit_in_coordinator(config: dict[str, Any]) -> None:
    config["run_coordinator"]["config"]["max_concurrent_runs"] = config["concurrency"]["runs"].pop(
        "max_concurrent_runs"
    )


def _misspell_top_level_key(config: dict[str, Any]) -> None:
    config["concurrancy"] = config.pop("concurrency")


@pytest.mark.parametrize(
    ("breakage", "expected"),
    [
        (_misspell_launcher_key, "job_namespce"),
        (_misspell_postgres_key, "db_nam"),
        (_misspell_coordinator_key, "dequeue_num_worker"),
        (_run_limit_in_coordinator, "max_concurrent_runs"),
        (_misspell_top_level_key, "concurrancy"),
    ],
    ids=["run_launcher", "storage", "run_coordinator", "run-limit-in-coordinator", "top-level"],
)
def test_broken_instance_yaml_fails(tmp_path: Path, pg_env: None, breakage: Any, expected: str) -> None:
    config = instance_yaml()
    breakage(config)
    with pytest.raises(DagsterInvalidConfigError, match=expected):
        validate_instance_yaml(write_instance(tmp_path, config), tmp_path)


def test_instance_schema_alone_misses_launcher_typos(tmp_path: Path) -> None:
    """Why the per-class check exists: the instance schema takes any mapping under ``config``."""
    config = instance_yaml()
    _misspell_launcher_key(config)
    load_instance_ref(write_instance(tmp_path, config), tmp_path)  # no error here


# --- deploy/k8s/values.yaml -------------------------------------------------------------------


def test_helm_values_load_the_k8s_location() -> None:
    values = yaml.safe_load(VALUES_YAML.read_text())
    (deployment,) = values["dagster-user-deployments"]["deployments"]
    args = deployment["dagsterApiGrpcArgs"]
    assert args[args.index("--module-name") + 1] == MODULE
    assert deployment["image"]["repository"] and deployment["image"]["tag"] not in ("", "latest")
    assert values["runLauncher"]["type"] == "K8sRunLauncher"
    assert values["dagsterDaemon"]["runCoordinator"]["type"] == "QueuedRunCoordinator"


def test_helm_values_match_instance_yaml() -> None:
    values = yaml.safe_load(VALUES_YAML.read_text())["concurrency"]
    instance = instance_yaml()["concurrency"]
    assert values["enabled"] is True
    assert values["pools"]["defaultLimit"] == instance["pools"]["default_limit"]
    assert values["pools"]["granularity"] == instance["pools"]["granularity"]
    assert values["runs"]["maxConcurrentRuns"] == instance["runs"]["max_concurrent_runs"]


# --- orchestration/k8s_definitions.py ---------------------------------------------------------


def test_definitions_validate_cli(tmp_path: Path) -> None:
    (tmp_path / "dagster.yaml").write_text("")
    env = {**os.environ, "DAGSTER_HOME": str(tmp_path)}
    dagster = Path(sys.executable).parent / "dagster"
    result = subprocess.run(
        [str(dagster), "definitions", "validate", "-m", MODULE, "-d", str(REPO)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_k8s_location_jobs_use_the_k8s_executor() -> None:
    from dagster_k8s import k8s_job_executor

    from orchestration.k8s_definitions import defs

    jobs = list(defs.resolve_all_job_defs())
    assert jobs
    for job in jobs:
        assert job.executor_def.name == k8s_job_executor.name, job.name
        resolved = job.executor_def.config_schema.resolve_config({})
        assert resolved.success, resolved.errors
        config = resolved.value["config"]
        assert config["max_concurrent"] >= 1
        assert config["step_k8s_config"]["container_config"]["resources"]["requests"]


def test_gpu_pool_steps_request_a_gpu() -> None:
    """A step in the "gpu" pool without a GPU limit would take a pool slot on a node with no GPU."""
    from orchestration.k8s_definitions import defs

    gpu_ops = {
        op_def.name: op_def
        for job in defs.resolve_all_job_defs()
        for op_def in job.graph.iterate_op_defs()
        if op_def.pool == "gpu"
    }
    assert gpu_ops, "no step uses pool='gpu'"
    for name, op_def in gpu_ops.items():
        k8s_config = op_def.tags.get(GPU_TAG)
        assert k8s_config, f"{name}: pool='gpu' but no {GPU_TAG} op tag"
        if isinstance(k8s_config, str):
            k8s_config = yaml.safe_load(k8s_config)
        assert k8s_config["container_config"]["resources"]["limits"]["nvidia.com/gpu"], name


def test_executor_namespace_follows_env() -> None:
    from orchestration.k8s_definitions import NAMESPACE_ENV, executor_config

    assert "job_namespace" not in executor_config({})
    assert executor_config({NAMESPACE_ENV: "gpu-farm"})["job_namespace"] == "gpu-farm"
