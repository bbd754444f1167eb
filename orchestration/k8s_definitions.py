"""The code location for Dagster on Kubernetes: each step of a run is its own k8s Job.

The Helm chart's user code deployment serves it (``dagster api grpc -m orchestration.k8s_definitions``,
see ``deploy/k8s/values.yaml``). The assets are the same as the local location's; only the executor
differs. GPU steps ask for a GPU through their ``dagster-k8s/config`` op tag, and the instance's
``gpu`` pool (``deploy/k8s/dagster.yaml``) caps how many of them run at once across all runs.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from dagster_k8s import k8s_job_executor

from orchestration.definitions import build_definitions

NAMESPACE_ENV = "MORPHEUS_K8S_NAMESPACE"
MAX_CONCURRENT_ENV = "MORPHEUS_K8S_MAX_CONCURRENT"

# Per run, not cluster-wide: a run over a large partition range would otherwise start one pod per
# ready step at once and flood the scheduler. The cluster-wide GPU cap is the "gpu" pool instead.
DEFAULT_MAX_CONCURRENT = 8

# Requests so the scheduler packs CPU steps sensibly. GPU assets' op tags deep-merge their
# nvidia.com/gpu limit on top, so GPU steps keep these requests as well.
STEP_K8S_CONFIG: Mapping[str, Any] = {
    "container_config": {
        "resources": {
            "requests": {"cpu": "2", "memory": "8Gi"},
            "limits": {"memory": "32Gi"},
        },
    },
}


def executor_config(environ: Mapping[str, str] = os.environ) -> dict[str, Any]:
    """The ``k8s_job_executor`` config, read from ``environ`` when the location loads."""
    config: dict[str, Any] = {
        "max_concurrent": int(environ.get(MAX_CONCURRENT_ENV, DEFAULT_MAX_CONCURRENT)),
        "step_k8s_config": STEP_K8S_CONFIG,
    }
    # Unset by default: step Jobs then follow the run launcher's job_namespace, where its service
    # account and the Postgres secret are. A fixed default would break installs into any other namespace.
    namespace = environ.get(NAMESPACE_ENV)
    if namespace:
        config["job_namespace"] = namespace
    return config


defs = build_definitions(executor=k8s_job_executor.configured(executor_config()))
