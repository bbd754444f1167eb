"""The Dagster UI shows the pipeline's asset graph, and a materialised photo's previews and check results.

``dagster-webserver`` serves the repository's real ``workspace.yaml`` on a loopback port; headless Chromium
(selenium driving the Debian ``chromium``/``chromium-driver`` packages) renders the global asset lineage page, and
the asset nodes and lineage edges read back from the rendered SVG must be those of
``orchestration.definitions.defs``. The UI draws an edge as a bare ``<path>`` (no ids or data attributes naming its
ends), so each edge is identified geometrically: its first point lies on the source node's ``<foreignObject>``
box, its last point (under the arrow head) just outside the target's.

The second test first materialises the six assets for ``mug.jpg`` (tiny configuration) into the instance the
webserver then serves, with the same ``MORPHEUS_*`` settings for its code location. On ``uv_asset``'s Partitions
tab (``/assets/uv_asset?view=partitions&partition=mug.jpg``) the partition's latest materialisation must be that
run's, and its metadata table must have a ``preview`` row. Dagster 1.13 renders Markdown metadata of 1000
characters or more (a base64 PNG always is) as a ``[Show Markdown]`` link opening a dialog with the rendered
Markdown; its sanitiser allows ``data:`` image sources, so the dialog's ``<img>`` must be the materialisation's PNG,
decoded by the browser (``naturalWidth`` > 0, the PNG's size). The Checks tab (``?view=checks``) must list
``uv_asset``'s checks with the run's pass/fail status, and each one's latest execution must be for ``mug.jpg``.

Skips only when Chromium, chromedriver or selenium are missing (``make browser``, a dependency of ``make test``,
installs the Debian packages). The screenshots go to ``benchmarks/results/dagster_asset_graph.png`` and
``dagster_asset_preview.png`` (the preview dialog open) when the file does not exist yet or
``MORPHEUS_UPDATE_SCREENSHOT=1``; otherwise to pytest's tmp dir.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.browser import chromium, needs_browser

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "benchmarks" / "results" / "dagster_asset_graph.png"
PREVIEW_SCREENSHOT = REPO / "benchmarks" / "results" / "dagster_asset_preview.png"
# The photo materialised (tiny configuration) for the preview test, the asset whose page is opened, and checks
# that must be listed there with their status.
PHOTO = "mug.jpg"
PREVIEW_ASSET = "uv_asset"
PREVIEW_CHECKS = ("reference_psnr", "uv_coverage")
PASSED_WORDS = {"Succeeded", "Passed"}  # how the Checks tab says passed (list, latest execution tag) ...
FAILED_WORDS = {"Failed"}  # ... and failed
# The pipeline's assets: the graph must show at least these (so an empty graph cannot pass).
PIPELINE_ASSETS = ("reference", "nerf_field", "dmtet_mesh", "refined_texture", "uv_asset", "qa_report")
# "Lineage" in the UI's navigation: the global asset lineage graph, every asset of every code location. With more
# than one asset group the UI collapses each group into one box unless it is listed in ``?expanded=`` (as
# ``global@global:<group>`` while the UI's per-code-location grouping flag is off, its default).
GRAPH_PATH = "/asset-groups"
VIEWPORT = (1600, 1000)  # below ~2250 px wide the UI draws the 7-column graph with its compact ("minimal") nodes
SERVE_TIMEOUT_S = 120.0  # webserver up and the code location loaded (slow first import on 2 cores)
RENDER_TIMEOUT_S = 60.0  # asset graph laid out and drawn
# An edge's ends are on (start) or a few units outside (end, under the arrow) its nodes' boxes; the gap between
# two ranks of the layout is ~60 units.
ENDPOINT_TOLERANCE = 25.0


pytestmark = needs_browser


# ---------------------------------------------------------------- expected graph, from the Definitions object


def _display_name(key) -> str:
    """The UI labels a graph node with the last component of its asset key."""
    return key.path[-1]


@dataclass(frozen=True)
class Expected:
    names: set[str]  # node labels
    edges: set[tuple[str, str]]  # (upstream, downstream)
    groups: set[str]


def expected_graph() -> Expected:
    """Every asset of ``orchestration.definitions.defs`` with its dependencies, as the UI should draw them."""
    from orchestration.definitions import defs

    graph = defs.resolve_asset_graph()
    keys = set(graph.get_all_asset_keys())
    names = {_display_name(key) for key in keys}
    assert len(names) == len(keys), f"asset keys share a last component, the UI labels would be ambiguous: {keys}"
    edges = {
        (_display_name(parent), _display_name(key))
        for key in keys
        for parent in graph.get(key).parent_keys
        if parent in keys and parent != key
    }
    return Expected(names, edges, groups={graph.get(key).group_name for key in keys})


@pytest.fixture
def expected() -> Expected:
    """Checked before the webserver starts: the definitions must hold the pipeline's assets."""
    graph = expected_graph()
    missing = sorted(set(PIPELINE_ASSETS) - graph.names)
    assert not missing, f"orchestration.definitions.defs lacks pipeline assets {missing} (has {sorted(graph.names)})"
    return graph


def graph_url(base: str, groups: set[str]) -> str:
    expanded = ",".join(f"global@global:{group}" for group in sorted(groups))
    return f"{base}{GRAPH_PATH}?{urllib.parse.urlencode({'expanded': expanded})}"


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


def _write_instance_config(home: Path) -> None:
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


@pytest.fixture
def webserver(tmp_path: Path) -> Iterator[str]:
    """The repository's code location with its default settings over an empty instance."""
    home = tmp_path / "dagster_home"
    _write_instance_config(home)
    with serve(home, tmp_path / "webserver.log") as base:
        yield base


# ---------------------------------------------------------------- the browser


@pytest.fixture
def browser() -> Iterator:
    with chromium(VIEWPORT) as driver:
        yield driver


# The graph's <svg> (the one holding <foreignObject> nodes): each node's box in SVG units and its own texts (an
# element's direct text, plus data-tooltip, which carries the untruncated name of a full-size node); each edge
# <path> (outside <defs> and nodes) by its first and last points.
SNAPSHOT_JS = """
const svg = Array.from(document.querySelectorAll('svg')).find((s) => s.querySelector('foreignObject'));
if (!svg) { return null; }
const num = (el, name) => parseFloat(el.getAttribute(name));
const nodes = Array.from(svg.querySelectorAll('foreignObject'))
  .filter((fo) => !fo.classList.contains('group'))
  .map((fo) => {
    const texts = new Set();
    for (const el of fo.querySelectorAll('*')) {
      if (el.dataset && el.dataset.tooltip) { texts.add(el.dataset.tooltip.trim()); }
      const own = Array.from(el.childNodes).filter((n) => n.nodeType === 3).map((n) => n.textContent).join('');
      if (own.trim()) { texts.add(own.trim()); }
    }
    return {x: num(fo, 'x'), y: num(fo, 'y'), w: num(fo, 'width'), h: num(fo, 'height'), texts: Array.from(texts)};
  });
const edges = Array.from(svg.querySelectorAll('path'))
  .filter((p) => !p.closest('defs, marker, foreignObject'))
  .map((p) => {
    const a = p.getPointAtLength(0);
    const b = p.getPointAtLength(p.getTotalLength());
    return {x1: a.x, y1: a.y, x2: b.x, y2: b.y, d: p.getAttribute('d')};
  });
return {nodes: nodes, edges: edges};
"""


@dataclass
class Box:
    x: float
    y: float
    w: float
    h: float

    def distance(self, px: float, py: float) -> float:
        dx = max(self.x - px, 0.0, px - (self.x + self.w))
        dy = max(self.y - py, 0.0, py - (self.y + self.h))
        return math.hypot(dx, dy)


def _label_matches(label: str, name: str) -> bool:
    """The UI middle-truncates long names with an ellipsis (``refined_…ture``)."""
    if label == name:
        return True
    head, sep, tail = label.partition("…")
    return bool(sep) and len(name) > len(head) + len(tail) and name.startswith(head) and name.endswith(tail)


@dataclass
class Rendered:
    nodes: dict[str, Box]  # asset name -> node box
    edges: set[tuple[str, str]]  # (upstream, downstream), from the paths' endpoints
    unattached: list[str]  # paths whose ends are not on two asset nodes
    ambiguous: list[str]  # node boxes whose texts match several asset names


def read_graph(snapshot: dict | None, names: set[str]) -> Rendered:
    rendered = Rendered(nodes={}, edges=set(), unattached=[], ambiguous=[])
    if not snapshot:
        return rendered
    for node in snapshot["nodes"]:
        matches = {name for name in names for label in node["texts"] if _label_matches(label, name)}
        if len(matches) == 1:
            rendered.nodes[matches.pop()] = Box(node["x"], node["y"], node["w"], node["h"])
        elif matches:
            rendered.ambiguous.append(f"{sorted(matches)} at ({node['x']}, {node['y']})")

    def nearest(px: float, py: float) -> str | None:
        if not rendered.nodes:
            return None
        name, box = min(rendered.nodes.items(), key=lambda item: item[1].distance(px, py))
        return name if box.distance(px, py) <= ENDPOINT_TOLERANCE else None

    for edge in snapshot["edges"]:
        upstream, downstream = nearest(edge["x1"], edge["y1"]), nearest(edge["x2"], edge["y2"])
        if upstream and downstream and upstream != downstream:
            rendered.edges.add((upstream, downstream))
        else:
            rendered.unattached.append(f"{edge['d']} ({upstream} -> {downstream})")
    return rendered


def _save_screenshot(driver, tmp_path: Path, rendered_ok: bool, kept: Path = SCREENSHOT) -> Path:
    """To ``kept`` (a screenshot in the repository) when it is missing or MORPHEUS_UPDATE_SCREENSHOT=1 and the page
    is right; otherwise to pytest's tmp dir."""
    target = tmp_path / kept.name
    if rendered_ok and (not kept.exists() or os.environ.get("MORPHEUS_UPDATE_SCREENSHOT") == "1"):
        target = kept
    target.parent.mkdir(parents=True, exist_ok=True)
    assert driver.save_screenshot(str(target)), f"could not write {target}"
    return target


# ---------------------------------------------------------------- the test


def test_ui_shows_asset_graph(expected: Expected, webserver: str, browser, tmp_path: Path) -> None:
    names, edges = expected.names, expected.edges
    started = time.monotonic()
    browser.get(graph_url(webserver, expected.groups))
    deadline = time.monotonic() + RENDER_TIMEOUT_S
    while True:
        rendered = read_graph(browser.execute_script(SNAPSHOT_JS), names)
        done = names <= rendered.nodes.keys() and rendered.edges == edges and not rendered.unattached
        if done or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    if done:
        time.sleep(1.0)  # let the nodes' status colours (a separate query) arrive before the screenshot
    shot = _save_screenshot(browser, tmp_path, rendered_ok=done)
    print(f"asset graph rendered in {time.monotonic() - started:.1f} s; screenshot {shot}")

    where = f"(page {browser.current_url!r}, title {browser.title!r}, screenshot {shot})"
    assert not rendered.ambiguous, f"nodes with several asset names: {rendered.ambiguous} {where}"
    assert names <= rendered.nodes.keys(), f"asset nodes not shown: {sorted(names - rendered.nodes.keys())} {where}"
    assert not rendered.unattached, f"edges not joining two asset nodes: {rendered.unattached} {where}"
    assert rendered.edges == edges, (
        f"lineage edges differ from the definitions: missing {sorted(edges - rendered.edges)}, "
        f"unexpected {sorted(rendered.edges - edges)} {where}"
    )


# ---------------------------------------------------------------- previews and checks of a materialised photo


@dataclass(frozen=True)
class Deployment:
    """An instance in which the six assets were materialised for ``PHOTO`` with the tiny configuration."""

    home: Path  # DAGSTER_HOME
    env: dict[str, str]  # the MORPHEUS_* settings the run used, for the webserver's code location
    run_id: str
    preview: str  # the ``data:image/png;base64,...`` URI in PREVIEW_ASSET's ``preview`` metadata
    preview_size: tuple[int, int]  # that PNG's width and height
    checks: dict[str, tuple[bool, str]]  # PREVIEW_ASSET's check name -> (passed, description) for PHOTO


def settings_env(settings) -> dict[str, str]:
    """The environment under which ``OrchestrationSettings.from_env`` reads ``settings`` back."""
    return {
        "MORPHEUS_PHOTO_DIR": settings.photo_dir,
        "MORPHEUS_STORE": settings.store_root,
        "MORPHEUS_PRESET": settings.preset,
        "MORPHEUS_SET": ";".join(settings.overrides),
        "MORPHEUS_SETTLE_S": str(settings.settle_seconds),
        "MORPHEUS_RETRIES": str(settings.max_retries),
        "MORPHEUS_RETRY_DELAY_S": str(settings.retry_delay_s),
    }


@pytest.fixture
def deployment(tmp_path: Path) -> Deployment:
    """All six assets of ``PHOTO`` materialised (tiny configuration) into a fresh instance, before any webserver."""
    import dagster as dg
    from PIL import Image

    from orchestration.definitions import build_definitions
    from orchestration.settings import OrchestrationSettings
    from tests.orchestration_helpers import check_evaluations, materializations, photo_folder, run_job, settings

    started = time.monotonic()
    root = tmp_path / "deployment"
    photo_folder(root, [PHOTO])
    tiny = settings(root)
    env = settings_env(tiny)
    assert OrchestrationSettings.from_env(env) == tiny, "the webserver's code location would differ from the run's"
    home = tmp_path / "dagster_home"
    _write_instance_config(home)
    with dg.DagsterInstance.from_config(str(home)) as instance:
        result = run_job(build_definitions(settings=tiny), instance, [PHOTO])  # registers the partition too
    assert result.success, f"materialising {PHOTO} failed"
    markdown = materializations(result)[(PREVIEW_ASSET, PHOTO)]["preview"].value
    match = re.search(r"\((data:image/png;base64,[A-Za-z0-9+/=]+)\)", markdown)
    assert match, f"{PREVIEW_ASSET}'s preview metadata has no inline PNG: {markdown[:200]!r}"
    with Image.open(io.BytesIO(base64.b64decode(match.group(1).partition(",")[2]))) as png:
        size = png.size
    checks = {
        e.check_name: (e.passed, e.description or "")
        for e in check_evaluations(result)
        if e.asset_key.to_user_string() == PREVIEW_ASSET and e.partition == PHOTO
    }
    assert set(PREVIEW_CHECKS) <= checks.keys(), f"{PREVIEW_ASSET} lacks checks {PREVIEW_CHECKS}: {sorted(checks)}"
    print(f"materialised {PHOTO} in {time.monotonic() - started:.1f} s (run {result.run_id})")
    return Deployment(home, env, result.run_id, match.group(1), size, checks)


@pytest.fixture
def deployment_webserver(deployment: Deployment, tmp_path: Path) -> Iterator[str]:
    """The repository's code location with the deployment's settings, over the deployment's instance."""
    with serve(deployment.home, tmp_path / "webserver.log", deployment.env) as base:
        yield base


def _poll(read, ready, timeout: float = RENDER_TIMEOUT_S, interval: float = 0.25):
    """``read()`` until ``ready`` of its value or ``timeout`` seconds; returns the last value."""
    deadline = time.monotonic() + timeout
    while True:
        value = read()
        if ready(value) or time.monotonic() > deadline:
            return value
        time.sleep(interval)


# The partition's detail pane on the asset's Partitions tab: the block holding the "Latest materialization" heading
# and the metadata table after it; each metadata row by its label (the <tr>'s first cell), the preview's cell.
PARTITION_DETAIL_JS = """
const runId = arguments[0];
const leaf = (text) => Array.from(document.querySelectorAll('body *'))
  .find((e) => e.childElementCount === 0 && e.textContent.trim() === text);
const heading = leaf('Latest materialization');
if (!heading) { return null; }
let panel = heading.parentElement;
while (panel && !panel.querySelector('table')) { panel = panel.parentElement; }
if (!panel) { return null; }
const rows = {};
for (const tr of panel.querySelectorAll('table tr')) {
  const cells = tr.querySelectorAll(':scope > td');
  if (cells.length >= 2) { rows[cells[0].innerText.trim()] = cells[1]; }
}
const cell = rows['preview'];
return {
  title: panel.innerText.trim().split('\\n')[0],
  labels: Object.keys(rows),
  run_linked: !!panel.querySelector(`a[href*="/runs/${runId}"]`),
  preview_text: cell ? cell.innerText.trim() : null,
  preview_cell: cell || null,
  preview_link: cell ? cell.querySelector('a') : null,
  inline_images: cell ? cell.querySelectorAll('img').length : 0,
};
"""

# The rendered Markdown (the UI's lazily loaded renderer) in an element (the preview's cell, or else the dialog titled
# "preview" that "[Show Markdown]" opens) and its <img> elements as the browser decoded them.
IMAGES_JS = """
const dialog = Array.from(document.querySelectorAll('[role=dialog]'))
  .find((d) => d.innerText.trim().split('\\n')[0] === 'preview');
const where = arguments[0] || dialog;
if (!where) { return null; }
const markdown = where.querySelector('.dagster-markdown');
return {
  rendered: !!markdown,
  html: (markdown || where).innerHTML.slice(0, 400),
  images: Array.from(where.querySelectorAll('img')).map((img) => ({
    src: img.getAttribute('src') || '', alt: img.alt, complete: img.complete,
    natural: [img.naturalWidth, img.naturalHeight], shown: [img.clientWidth, img.clientHeight],
  })),
};
"""

# The Checks tab: each check in its left-hand list with the status line under its name; the selected check's
# "Latest execution" fields (a heading, its value in the next element).
CHECK_LIST_JS = """
return Array.from(document.querySelectorAll('[class*="checkRow"]')).map((row) => {
  const lines = row.innerText.trim().split('\\n');
  const named = row.querySelector('[title]');
  return {name: named ? named.getAttribute('title') : lines[0], status: lines[lines.length - 1], row: row};
});
"""
CHECK_DETAIL_JS = """
const leaf = (text) => Array.from(document.querySelectorAll('body *'))
  .find((e) => e.childElementCount === 0 && e.textContent.trim() === text);
const after = (text) => {
  const heading = leaf(text);
  return heading && heading.nextElementSibling ? heading.nextElementSibling.innerText.trim() : null;
};
return {result: after('Evaluation result'), partition: after('Partition'), text: document.body.innerText};
"""


def asset_url(asset: str, **params: str) -> str:
    return f"/assets/{urllib.parse.quote(asset)}?{urllib.parse.urlencode(params)}"


def _read_checks(browser, base: str, deployment: Deployment) -> dict[str, dict[str, str | None]]:
    """Each check of PREVIEW_ASSET as the Checks tab shows it: its status in the list and, once selected, its
    latest execution's result and partition, and its description when shown."""
    browser.get(f"{base}{asset_url(PREVIEW_ASSET, view='checks')}")
    expected = set(deployment.checks)
    rows = _poll(lambda: browser.execute_script(CHECK_LIST_JS), lambda rs: expected <= {r["name"] for r in rs})
    seen: dict[str, dict[str, str | None]] = {r["name"]: {"listed": r["status"]} for r in rows}
    for name in sorted(expected & seen.keys()):
        row = next(r["row"] for r in browser.execute_script(CHECK_LIST_JS) if r["name"] == name)
        row.click()
        description = deployment.checks[name][1]
        detail = _poll(
            lambda: browser.execute_script(CHECK_DETAIL_JS),
            lambda d, description=description: bool(d["result"] and d["partition"] and description in d["text"]),
        )
        seen[name].update(result=detail["result"], partition=detail["partition"],
                          description=description if description in detail["text"] else None)
    return seen


def test_ui_shows_previews_and_checks(deployment: Deployment, deployment_webserver: str, browser,
                                      tmp_path: Path) -> None:
    base = deployment_webserver
    started = time.monotonic()

    # The checks first (the page the screenshot shows is the partition's, with the preview open).
    checks = _read_checks(browser, base, deployment)
    checked_at = time.monotonic()
    where = f"(page {browser.current_url!r})"
    for name, (passed, description) in deployment.checks.items():
        shown = checks.get(name, {})
        words = PASSED_WORDS if passed else FAILED_WORDS
        assert shown.get("listed") in words, f"check {name} (passed={passed}) listed as {shown.get('listed')!r} {where}"
        assert shown.get("result") in words, f"check {name} (passed={passed}) result {shown.get('result')!r} {where}"
        assert shown.get("partition") == PHOTO, f"check {name}: latest execution for {shown.get('partition')!r}"
        assert shown.get("description") == description, f"check {name}: description {description!r} not shown"

    # The partition's latest materialisation and its metadata table.
    browser.get(f"{base}{asset_url(PREVIEW_ASSET, view='partitions', partition=PHOTO)}")
    detail = _poll(
        lambda: browser.execute_script(PARTITION_DETAIL_JS, deployment.run_id),
        lambda d: bool(d and d["run_linked"] and (d["preview_link"] or d["inline_images"])),
    )
    where = f"(page {browser.current_url!r}, title {browser.title!r})"
    assert detail, f"no 'Latest materialization' with a metadata table for {PHOTO} {where}"
    assert detail["title"] == PHOTO, f"partition detail of {detail['title']!r}, not {PHOTO} {where}"
    assert detail["run_linked"], f"the latest materialisation shown is not run {deployment.run_id} {where}"
    assert "preview" in detail["labels"], f"no preview row in the metadata table: {detail['labels']} {where}"
    if not detail["inline_images"]:
        # Dagster 1.13 shows Markdown metadata of 1000 characters or more as a "[Show Markdown]" link that opens
        # the rendered Markdown in a dialog; a preview PNG is always longer than that.
        assert detail["preview_text"] == "[Show Markdown]", f"preview cell: {detail['preview_text']!r} {where}"
        browser.execute_script("arguments[0].scrollIntoView({block: 'center'});", detail["preview_cell"])
        detail["preview_link"].click()
    images = _poll(
        lambda: browser.execute_script(IMAGES_JS, detail["preview_cell"] if detail["inline_images"] else None),
        # The Markdown renderer is loaded lazily: once it has rendered, no <img> is final (a sanitiser dropped it).
        lambda i: bool(i and i["rendered"]) and all(img["complete"] for img in i["images"]),
    )
    time.sleep(0.5)  # the dialog's opening transition, before the screenshot
    rendered = time.monotonic()
    shown = images["images"] if images else []
    ok = len(shown) == 1 and shown[0]["src"] == deployment.preview and shown[0]["natural"][0] > 0
    shot = _save_screenshot(browser, tmp_path, rendered_ok=ok, kept=PREVIEW_SCREENSHOT)
    print(f"checks read in {checked_at - started:.1f} s, preview shown in {rendered - checked_at:.1f} s; "
          f"screenshot {shot}")

    where = f"(page {browser.current_url!r}, screenshot {shot})"
    assert images is not None, f"no 'preview' dialog opened {where}"
    assert len(shown) == 1, (
        f"expected one <img> in the rendered preview, got {shown}: the UI's Markdown renderer dropped the image? "
        f"Rendered: {images['html']!r} {where}"
    )
    img = shown[0]
    assert img["src"].startswith("data:image/png;base64,"), (
        f"the preview's <img> src is {img['src'][:60]!r}: Dagster's Markdown renderer dropped the data URI {where}"
    )
    assert img["src"] == deployment.preview, f"the <img> is not the materialisation's preview PNG {where}"
    assert img["natural"][0] > 0, f"the browser did not decode the preview PNG: {img} {where}"
    assert tuple(img["natural"]) == deployment.preview_size, f"decoded {img}, the PNG is {deployment.preview_size}"
    assert img["shown"][0] > 0 and img["shown"][1] > 0, f"the preview is not laid out visibly: {img} {where}"
