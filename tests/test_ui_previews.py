"""The Dagster UI shows a materialised photo's previews and check results.

The test first materialises the six assets for ``mug.jpg`` (tiny configuration) into the instance the
webserver then serves, with the same ``MORPHEUS_*`` settings for its code location. On ``bake``'s Partitions
tab (``/assets/bake?view=partitions&partition=mug.jpg``) the partition's latest materialisation must be that
run's, and its metadata table must have a ``preview`` row. Dagster 1.13 renders Markdown metadata of 1000
characters or more (a base64 PNG always is) as a ``[Show Markdown]`` link opening a dialog with the rendered
Markdown; its sanitiser allows ``data:`` image sources, so the dialog's ``<img>`` must be the materialisation's PNG,
decoded by the browser (``naturalWidth`` > 0, the PNG's size). The Checks tab (``?view=checks``) must list
``bake``'s checks with the run's pass/fail status, and each one's latest execution must be for ``mug.jpg``.

Skips only when Chromium, chromedriver or selenium are missing (``make browser``, a dependency of ``make test``,
installs the Debian packages). The screenshot (the preview dialog open) goes to
``benchmarks/results/dagster_asset_preview.png`` when the file does not exist yet or
``MORPHEUS_UPDATE_SCREENSHOT=1``; otherwise to pytest's tmp dir.
"""

from __future__ import annotations

import base64
import io
import re
import time
import urllib.parse
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.browser import chromium, needs_browser
from tests.dagster_ui import (
    PREVIEW_SCREENSHOT,
    RENDER_TIMEOUT_S,
    VIEWPORT,
    save_screenshot,
    serve,
    write_instance_config,
)

# The photo materialised (tiny configuration) for the preview test, the asset whose page is opened, and checks
# that must be listed there with their status.
PHOTO = "mug.jpg"
PREVIEW_ASSET = "bake"
PREVIEW_CHECKS = ("reference_psnr", "uv_coverage")
PASSED_WORDS = {"Succeeded", "Passed"}  # how the Checks tab says passed (list, latest execution tag) ...
FAILED_WORDS = {"Failed"}  # ... and failed


pytestmark = needs_browser


# ---------------------------------------------------------------- the browser


@pytest.fixture
def browser() -> Iterator:
    with chromium(VIEWPORT) as driver:
        yield driver


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
    write_instance_config(home)
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
    shot = save_screenshot(browser, tmp_path, rendered_ok=ok, kept=PREVIEW_SCREENSHOT)
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
