"""The Dagster UI for the browser tests (``tests/test_ui_graph.py``, ``tests/test_ui_previews.py``):
``dagster-webserver`` serving the repository's real ``workspace.yaml`` on a free loopback port over a given
instance, and the screenshots, kept in ``benchmarks/results/`` when missing there or
``MORPHEUS_UPDATE_SCREENSHOT=1``, otherwise written to pytest's tmp dir."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "benchmarks" / "results" / "dagster_asset_graph.png"
PREVIEW_SCREENSHOT = REPO / "benchmarks" / "results" / "dagster_asset_preview.png"
VIEWPORT = (1600, 1000)  # below ~2250 px wide the UI draws the 7-column graph with its compact ("minimal") nodes
SERVE_TIMEOUT_S = 120.0  # webserver up and the code location loaded (slow first import on 2 cores)
RENDER_TIMEOUT_S = 60.0  # asset graph laid out and drawn


# ---------------------------------------------------------------- the webserver


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _log_tail(log: Path, lines: int = 40) -> str:
    text = log.read_text(errors="replace") if log.exists() else ""
    return "\n".join(text.splitlines()[-lines:])


def _location_status(base: str) -> list[dict] | None:
    """The workspace's code locations (name, loadStatus, error message), or None while the server does not answer."""
    query = (
        "{ workspaceOrError { __typename ... on Workspace { locationEntries { name loadStatus "
        "locationOrLoadError { __typename ... on PythonError { message } } } } } }"
    )
    request = urllib.request.Request(
        f"{base}/graphql", data=json.dumps({"query": query}).encode(), headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            workspace = json.load(response)["data"]["workspaceOrError"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return workspace.get("locationEntries")


def write_instance_config(home: Path) -> None:
    """A Dagster instance in ``home`` (``dagster.yaml``) quiet enough for screenshots."""
    home.mkdir(parents=True, exist_ok=True)
    # No telemetry, and no "Join the Dagster community" dialog over the pages.
    (home / "dagster.yaml").write_text("telemetry:\n  enabled: false\nnux:\n  enabled: false\n")


@contextlib.contextmanager
def serve(home: Path, log: Path, env: Mapping[str, str] | None = None) -> Iterator[str]:
    """``dagster-webserver -w workspace.yaml`` on a free loopback port over the instance in ``home`` (extra
    environment ``env``); yields its base URL once the code location has loaded. Killed with its process group (the
    code server is a child) even when the test fails."""
    exe = Path(sys.executable).with_name("dagster-webserver")
    assert exe.exists(), f"{exe} missing: dagster-webserver is a dependency (pip install -e '.[dev]')"
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    full_env = dict(os.environ, **(env or {}), DAGSTER_HOME=str(home))
    full_env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH")) if p)
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [str(exe), "-w", "workspace.yaml", "-h", "127.0.0.1", "-p", str(port)],
            cwd=REPO,
            env=full_env,
            stdout=out,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            start_new_session=True,
        )
    try:
        deadline = time.monotonic() + SERVE_TIMEOUT_S
        while True:
            assert proc.poll() is None, f"dagster-webserver exited with {proc.returncode}:\n{_log_tail(log)}"
            entries = _location_status(base)
            if entries:
                errors = [e for e in entries if e["locationOrLoadError"]["__typename"] == "PythonError"]
                assert not errors, f"code location failed to load: {errors}\n{_log_tail(log)}"
                if all(e["loadStatus"] == "LOADED" for e in entries):
                    break
            assert time.monotonic() < deadline, (
                f"dagster-webserver did not serve a loaded workspace within {SERVE_TIMEOUT_S:.0f} s "
                f"(locations: {entries}):\n{_log_tail(log)}"
            )
            time.sleep(0.5)
        yield base
    finally:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=20)
        except ProcessLookupError:
            pass
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(timeout=10)


def save_screenshot(driver: Any, tmp_path: Path, rendered_ok: bool, kept: Path = SCREENSHOT) -> Path:
    """Save the browser's screenshot to ``kept`` (a screenshot in the repository) when it is missing or
    MORPHEUS_UPDATE_SCREENSHOT=1 and the page is right; otherwise to pytest's tmp dir. Returns where it went."""
    target = tmp_path / kept.name
    if rendered_ok and (not kept.exists() or os.environ.get("MORPHEUS_UPDATE_SCREENSHOT") == "1"):
        target = kept
    target.parent.mkdir(parents=True, exist_ok=True)
    assert driver.save_screenshot(str(target)), f"could not write {target}"
    return target
