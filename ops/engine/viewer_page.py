"""The page per asset people can turn (the ``qa`` stage writes it beside ``qa.json``): the web GLB at its real size
in ``<model-viewer>``, the photo, the dimensions and the QA verdict (``ops.reporting.gallery`` links them all).

``<model-viewer>`` (Google, Apache-2.0) comes from npm (``tools/web``, ``make web-tools``) and is copied once per
store into ``<store>/.viewer/`` (the leading dot keeps it out of the photo keys), so the pages work offline from
the file system or any static server, with no CDN. A page whose script is missing says so and how to fix it.
The meshopt decoder sits beside it for the web GLB's compressed geometry. The web GLB is inside the page as a
data URI: browsers refuse to fetch a file:// model from a file:// page, and a page opened from the Dagster UI
or a file manager is exactly that.
"""

from __future__ import annotations

import base64
from collections.abc import Sequence
from dataclasses import dataclass
from html import escape
from pathlib import Path

from assets_store.atomic import atomic_write_bytes, atomic_write_text
from morpheus_core.export.web_tools import web_tool

VIEWER_DIR = ".viewer"
VIEWER_FILE = "viewer.html"
# The UMD build is a classic script: browsers refuse module scripts from file:// pages.
MODEL_VIEWER_JS = "@google/model-viewer/dist/model-viewer-umd.min.js"
# A classic script defining ``self.MeshoptDecoder``, which model-viewer loads from ``meshoptDecoderLocation``.
MESHOPT_DECODER_JS = "meshoptimizer/meshopt_decoder.cjs"
VENDORED = {MODEL_VIEWER_JS: "model-viewer.min.js", MESHOPT_DECODER_JS: "meshopt_decoder.js"}


def vendor_viewer(store_root: Path) -> str | None:
    """Copy ``<model-viewer>`` and the meshopt decoder into ``<store_root>/.viewer/`` unless the same files are
    there; None when done, else why not (the pages then show the message)."""
    target = Path(store_root) / VIEWER_DIR
    for rel, name in VENDORED.items():
        try:
            source = web_tool(rel)
        except FileNotFoundError as exc:
            return str(exc)
        dest = target / name
        data = source.read_bytes()
        if not dest.is_file() or dest.read_bytes() != data:
            atomic_write_bytes(dest, data)
    return None


@dataclass(frozen=True)
class ViewerPage:
    """What one asset's page shows; the ``*_href`` are relative to the page."""

    title: str
    web_glb: bytes
    glb_href: str
    usdz_href: str | None
    photo_href: str | None
    script_dir_href: str
    size_mm: dict[str, float]
    verdict: str
    reasons: Sequence[str] = ()
    scale_source: str = ""
    sku: str = ""


PAGE_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0 auto;max-width:1200px;padding:1em 2em;
color:#222}
.row{display:flex;flex-wrap:wrap;gap:1.5em;align-items:flex-start}
model-viewer{width:520px;height:520px;background:#f4f4f4;border:1px solid #ddd}
img.photo{width:240px;border:1px solid #ddd}
figure{margin:0 0 1em 0}
.side{flex:1 1 280px;min-width:260px}
.verdict{display:inline-block;padding:.1em .6em;border-radius:.3em;font-weight:600}
.pass{background:#d8f5d8}.warn{background:#fff1c4}.fail{background:#ffd6d6}
dl{display:grid;grid-template-columns:max-content auto;gap:.2em 1em}dt{color:#555}dd{margin:0}
#missing{display:none;background:#fff4d6;border:1px solid #e0b84a;padding:.4em 1em}
"""


def viewer_html(page: ViewerPage) -> str:
    """The page as a string (every text from the catalog escaped)."""
    size = page.size_mm
    dims = " × ".join(f"{size[k]:.0f}" for k in ("width", "height", "depth") if k in size)
    ar = f' ios-src="{escape(page.usdz_href)}"' if page.usdz_href else ""
    photo = (f'<figure><img class="photo" src="{escape(page.photo_href)}" alt="the photo"><figcaption>the photo'
             f'</figcaption></figure>') if page.photo_href else ""
    reasons = "".join(f"<li>{escape(r)}</li>" for r in page.reasons)
    links = f'<a href="{escape(page.glb_href)}" download>GLB</a>'
    if page.usdz_href:
        links += f' · <a href="{escape(page.usdz_href)}" download>USDZ</a>'
    script = f"{page.script_dir_href.rstrip('/')}/"
    model = base64.b64encode(page.web_glb).decode()
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">"
        f"<title>{escape(page.title)}</title><style>{PAGE_CSS}</style>"
        f'<script src="{escape(script)}model-viewer.min.js"></script></head><body>'
        # The decoder's location (default: a CDN), set on the element's class before any element is made; it
        # loads the decoder by adding a script to the body, so this runs inside the body.
        "<script>if(customElements.get('model-viewer'))customElements.get('model-viewer').meshoptDecoderLocation="
        f"'{escape(script)}meshopt_decoder.js';</script>"
        f"<h1>{escape(page.title)}</h1>"
        f'<p id="missing">The 3D viewer\'s script is missing ({escape(script)}model-viewer.min.js): run '
        "<code>make web-tools</code> and then the pipeline again, or open the GLB below in any glTF viewer.</p>"
        f'<div class="row"><model-viewer src="data:model/gltf-binary;base64,{model}"{ar} alt="{escape(page.title)}" '
        'camera-controls '
        'touch-action="pan-y" ar ar-modes="webxr scene-viewer quick-look" shadow-intensity="1" '
        'interaction-prompt="none"></model-viewer>'
        f"<div class=\"side\">{photo}<dl><dt>size (W × H × D)</dt><dd>{escape(dims)} mm</dd>"
        f"<dt>size from</dt><dd>{escape(page.scale_source or 'unknown')}</dd>"
        + (f"<dt>SKU</dt><dd>{escape(page.sku)}</dd>" if page.sku else "")
        + f'<dt>QA</dt><dd><span class="verdict {escape(page.verdict)}">{escape(page.verdict)}</span></dd>'
        f"<dt>files</dt><dd>{links}</dd></dl>"
        + (f"<ul>{reasons}</ul>" if reasons else "")
        + "</div></div>"
        # window.viewerState tells a test (or a person in the console) whether the model loaded.
        "<script>self.viewerState={loaded:false,error:null};const mv=document.querySelector('model-viewer');"
        "mv.addEventListener('load',()=>{viewerState.loaded=true;});"
        "mv.addEventListener('error',e=>{viewerState.error=String((e.detail&&e.detail.sourceError)||e.type);});"
        "</script>"
        # A script that did not load leaves the element undefined: say so rather than show an empty box.
        "<script>window.addEventListener('load',()=>setTimeout(()=>{if(!customElements.get('model-viewer'))"
        "document.getElementById('missing').style.display='block';},500));</script>"
        "</body></html>\n"
    )


def write_viewer(path: Path, page: ViewerPage) -> Path:
    return atomic_write_text(Path(path), viewer_html(page))
