"""The ``morpheus3d`` command line. Subcommands grow with the pipeline; none imports Dagster."""

from __future__ import annotations

import argparse
import datetime as dt
import importlib
import importlib.metadata as md
import json
import platform
import re
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from morpheus_core.priors.registry import PRIOR_MODELS, ModelRegistry, rembg_model_file
from ops.config.preset_names import PRESET_NAMES
from ops.migrations import current_stage_id
from ops.stages import STAGE_IDS

PACKAGES = (
    "torch", "numpy", "diffusers", "transformers", "peft", "safetensors", "dagster", "dagster-webserver",
    "trimesh", "xatlas", "pillow", "opencv-contrib-python-headless", "rembg", "onnxruntime", "pyarrow",
)


def package_version() -> str:
    try:
        return md.version("morpheus3d-batch")
    except md.PackageNotFoundError:
        return "0+unknown"


def _version_of(dist: str) -> str:
    try:
        return md.version(dist)
    except md.PackageNotFoundError:
        return "MISSING"


def cv2_status() -> tuple[bool, str]:
    """(is the contrib build, detail). rembg or others can pull the plain build over it."""
    try:
        cv2 = importlib.import_module("cv2")
    except ImportError as exc:
        return False, f"cv2 does not import: {exc}"
    contrib = hasattr(cv2, "ximgproc") and hasattr(cv2, "saliency")
    plain = [d for d in ("opencv-python-headless", "opencv-python") if _version_of(d) != "MISSING"]
    detail = f"cv2 {cv2.__version__}, contrib modules {'present' if contrib else 'ABSENT'}"
    if plain:
        detail += f"; also installed: {', '.join(plain)} (may shadow contrib; run `make install`)"
    return contrib, detail


def doctor() -> int:
    """Print versions, CUDA, the cv2 build and the model folders; exit 1 if the install is broken."""
    import torch

    ok = True
    print(f"morpheus3d {package_version()} on Python {platform.python_version()} ({platform.machine()})")
    print("\nPackages:")
    for dist in PACKAGES:
        v = _version_of(dist)
        ok &= v != "MISSING"
        print(f"  {dist:<32} {v}")
    print("\nCompute:")
    if torch.cuda.is_available():
        names = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
        print(f"  CUDA available: yes ({torch.version.cuda}; {names})")
    else:
        print(f"  CUDA available: no (CPU only; torch {torch.__version__}, {torch.get_num_threads()} threads)")
    from ops.engine.gpu_lease import GPUS_ENV, SLOTS_ENV, GpuLeaseError, LeaseSettings, gpu_count, gpu_slots

    try:
        leases = f"{gpu_count()} GPU(s) × {gpu_slots()} run(s) each ({GPUS_ENV}, {SLOTS_ENV}; locks in " \
                 f"{LeaseSettings().folder})"
    except GpuLeaseError as exc:
        ok, leases = False, f"bad setting: {exc}"
    print(f"  GPU leases: {leases}")
    contrib, detail = cv2_status()
    ok &= contrib
    print(f"  OpenCV: {detail}")
    registry = ModelRegistry()
    root, source = registry.resolved_root()
    print(f"\nModel folders (root {root}, from {source}; nothing is ever downloaded):")
    for status in registry.statuses():
        state = "present" if status.present else "missing"
        print(f"  {status.spec.name:<18} {state:<8} {status.path}  — {status.spec.purpose}")
        for miss in status.missing:
            print(f"      expected file: {miss}")
        if not status.present:
            print(f"      to provide it: {status.spec.how_to.replace('<folder>', str(status.path))}")
    print("\nPriors (weights missing → the weight-free proxy prior is the only one available):")
    for role, names in PRIOR_MODELS.items():
        state = "ready" if registry.prior_ready(role) else "weights missing"
        print(f"  {role} prior {state:<16} needs {', '.join(names)}")
    u2 = rembg_model_file()
    print(f"  {'rembg u2net':<18} {'present' if u2.is_file() else 'missing':<8} {u2}  — segmentation "
          "(set $U2NET_HOME; without it the classical fallback segments)")
    from morpheus_core.metrics.weighted import weighted_metric_status

    print("\nQA metrics with weights (missing → recorded as skipped in qa.json, never downloaded):")
    for status in weighted_metric_status():
        state = "present" if status.present else "missing"
        print(f"  {status.spec.name:<18} {state:<8} {status.path}  — {status.spec.purpose}")
        for miss in status.missing:
            print(f"      expected file: {miss}")
    print("\nStatus:", "OK" if ok else "BROKEN INSTALL (see above)")
    return 0 if ok else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="morpheus3d", description="Product photos to textured 3D assets.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.add_parser("doctor", help="check the installation, CUDA, OpenCV build and model folders")
    prep = sub.add_parser("prepare", help="photo(s) -> recentred RGBA + mask references, reference.json, plan.json")
    prep.add_argument("photo", type=Path, help="a photo, or a folder of photos (one output folder per photo)")
    prep.add_argument("--out", type=Path, required=True, help="output folder (for a folder of photos: its parent)")
    leniency = prep.add_mutually_exclusive_group()
    leniency.add_argument("--allow-failures", action="store_true",
                          help="exit 0 even when photos failed (a folder where some bad files are expected); "
                               "the outcome table still names them")
    # The default since a failed photo always exits 1; kept so that scripts passing it keep working.
    leniency.add_argument("--strict", action="store_true", help="exit 1 when any photo failed (the default)")
    prep.add_argument("--force", action="store_true", help="redo photos whose reference is already up to date")
    prep.add_argument("--rembg-model", type=Path, help="u2net .onnx file or folder (default: $U2NET_HOME)")
    prep.add_argument("--no-rembg", action="store_true", help="skip rembg; use the classical chain")
    prep.add_argument("--border-ratio", type=float, default=0.1, help="empty margin per side (default 0.1)")
    prep.add_argument("--max-megapixels", type=float, default=40.0, help="refuse larger photos (default 40)")
    prep.add_argument("--hf-threshold", type=float, default=0.08, help="skip high-pass refinement below this")
    prep.add_argument("--min-confidence", type=float, default=None,
                      help="stop a photo whose mask confidence is below this (default: SegmentConfig's; 0 accepts all)")
    run = sub.add_parser("run", help="photo(s) -> textured GLB: every stage, cached and resumable, in --out")
    # Optional in the parser so that --list-keys works alone; run_command requires them otherwise.
    run.add_argument("photo", type=Path, nargs="?", help="a photo, or a folder of photos (not needed with "
                     "--list-keys)")
    run.add_argument("--out", type=Path, help="the asset store: <out>/<photo-key>/<stage>/ (required unless "
                     "--list-keys)")
    run.add_argument("--preset", default="draft", choices=PRESET_NAMES,
                     help="schedule and sizes (draft: minutes on a CPU; paper: the paper's schedule on a GPU)")
    run.add_argument("--init-mesh", type=Path, help="refine an existing asset (GLB/OBJ): skips the NeRF stage")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override any setting, e.g. --set nerf.loop.steps=300 --set texture.guidance.k2d=0")
    run.add_argument("--device", help="cpu, cuda, cuda:1 … (default: auto)")
    run.add_argument("--until", default=STAGE_IDS[-1], type=current_stage_id, choices=STAGE_IDS,
                     help="stop after this stage")
    run.add_argument("--batch", type=int, default=1, metavar="N",
                     help="optimise N photos together: they share each prior forward, outputs as one by one. "
                          "On a GPU, 4-8 photos per batch (higher throughput); on a CPU keep 1 (default). A killed "
                          "batch resumes only when re-run with the same photos")
    run.add_argument("--list-keys", action="store_true", help="print every overridable setting (with the "
                     "--preset's value and --set's applied) and exit; needs no photo or --out")
    rep = sub.add_parser("report", help="the run catalog as one self-contained HTML page")
    rep.add_argument("--store", type=Path, help="the asset store (catalog at <store>/.catalog/; relative paths in "
                     "the catalog's rows are relative to it)")
    rep.add_argument("--catalog", type=Path, help="the catalog folder (default: <store>/.catalog/)")
    rep.add_argument("--no-compact", action="store_true", help="do not merge past days' catalog files first")
    rep.add_argument("--since", metavar="YYYY-MM-DD", help="only rows created on or after this UTC day")
    rep.add_argument("--out", type=Path, required=True, help="the HTML file to write")
    return parser


def parse_day(text: str) -> dt.date:
    """A YYYY-MM-DD day, strictly (date.fromisoformat alone also takes 20240101 and week dates)."""
    if not re.fullmatch(r"\d{4}-\d{2}-\d{2}", text):
        raise ValueError(f"{text!r} is not a date in the form YYYY-MM-DD")
    try:
        return dt.date.fromisoformat(text)
    except ValueError as exc:
        raise ValueError(f"{text!r} is not a valid date: {exc}") from None


def report_command(args: argparse.Namespace) -> int:
    """Write the catalog report; exit 2 on bad arguments, 1 when the catalog cannot be read."""
    from assets_store.catalog import Catalog
    from assets_store.catalog_files import CatalogError
    from assets_store.store import Store
    from ops.reporting.asset_metrics import asset_rows
    from ops.reporting.gallery import GALLERY_FILE, gallery_assets, gallery_html
    from ops.reporting.report import build_report, write_report
    from ops.reporting.report_sections import ReportOptions

    if args.store is None and args.catalog is None:
        print("morpheus3d report: give --store DIR (or --catalog DIR)", file=sys.stderr)
        return 2
    since = None
    if args.since is not None:
        try:
            since = parse_day(args.since)
        except ValueError as exc:
            print(f"morpheus3d report: --since {exc}", file=sys.stderr)
            return 2
    if args.store is not None and not args.store.is_dir():
        print(f"morpheus3d report: --store {args.store}: no such folder", file=sys.stderr)
        return 2
    if args.catalog is not None and not args.catalog.is_dir():
        # Named explicitly, a missing folder is a typo; a store without a catalog yet just has no runs.
        print(f"morpheus3d report: --catalog {args.catalog}: no such folder", file=sys.stderr)
        return 2
    root = args.catalog if args.catalog is not None else Store(args.store).catalog_dir
    base = args.store if args.store is not None else root.parent
    try:
        catalog = Catalog(root)
        if root.is_dir() and not args.no_compact:
            # One file per append: a large catalog reads ~1 ms per file, so merge past days first
            # (atomic, safe beside running writers; today's files stay as they are).
            done = catalog.compact()
            if done.files_merged:
                print(f"compacted {done.files_merged} catalog files of {len(done.days)} past day(s)", file=sys.stderr)
        options = ReportOptions(page_dir=args.out.resolve().parent)
        scanned = catalog.scan(since)  # once, for the report and the gallery
        page = build_report(catalog, since=since, base_dir=base, options=options, scanned=scanned)
        assets = asset_rows(scanned.table).to_pylist()
    except CatalogError as exc:
        print(f"morpheus3d report: {exc}", file=sys.stderr)
        return 1
    write_report(args.out, page)
    gallery = args.out.with_name(GALLERY_FILE)
    write_report(gallery, gallery_html(gallery_assets(assets, base.resolve(), gallery.resolve().parent)))
    print(f"wrote {args.out} and {gallery} (every asset's 3D viewer, filterable by verdict)", file=sys.stderr)
    return 0


def run_command(args: argparse.Namespace) -> int:
    """Run the pipeline over one photo or a folder; print the per-photo outcome table."""
    import logging

    from assets_store.keys import assign_keys
    from ops.config.presets import preset
    from ops.engine.config_tree import ConfigError, describe_keys, to_dict
    from ops.engine.store_layout import open_store
    from ops.intake.photo_folder import list_photos
    from ops.intake.products import ProductsFileError, products_for
    from ops.pipeline.runner import Pipeline, stages_until
    from ops.reporting.catalog_rows import record_outcomes
    from ops.reporting.progress import ConsoleProgress
    from ops.reporting.run_table import format_run_table

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if args.batch < 1:
        print(f"morpheus3d run: --batch must be at least 1 (photos optimised together), got {args.batch}",
              file=sys.stderr)
        return 2
    overrides = list(args.overrides) + ([f"device={args.device}"] if args.device else [])
    try:
        cfg = preset(args.preset, overrides)
    except (ConfigError, ValueError) as exc:
        print(f"morpheus3d run: {exc}", file=sys.stderr)
        return 2
    if args.list_keys:
        for key, value, doc in describe_keys(cfg):
            print(f"{key:<52} {json.dumps(to_dict(value), default=str):<12} {doc}")
        return 0
    missing = [what for what, value in (("a photo or folder", args.photo), ("--out", args.out)) if value is None]
    if missing:
        print(f"morpheus3d run: give {' and '.join(missing)} (usage: morpheus3d run PHOTO --out STORE; "
              "morpheus3d run --list-keys needs neither)", file=sys.stderr)
        return 2
    if args.init_mesh is not None and not args.init_mesh.is_file():
        print(f"morpheus3d run: --init-mesh {args.init_mesh}: no such file", file=sys.stderr)
        return 2
    if args.photo.is_dir():
        photos = list_photos(args.photo)
        if not photos:
            print(f"morpheus3d run: {args.photo} holds no photos (.jpg, .png, .webp, …)", file=sys.stderr)
            return 2
    elif args.photo.is_file():
        photos = [args.photo]
    else:
        print(f"morpheus3d run: {args.photo}: no such file or folder", file=sys.stderr)
        return 2
    try:  # rows naming no photo fail nobody's export: say them here (a bad file fails each export with its error)
        table = products_for(photos[0])
        for problem in table.unknown if table is not None else ():
            print(f"morpheus3d run: {problem}", file=sys.stderr)
    except ProductsFileError as exc:
        print(f"morpheus3d run: {exc}", file=sys.stderr)
    keys = assign_keys(p.name for p in photos)
    store = open_store(args.out)
    pipeline = Pipeline(store, cfg, args.preset, args.init_mesh, ConsoleProgress())
    outcomes = []
    groups = [photos[i:i + args.batch] for i in range(0, len(photos), args.batch)]
    for i, group in enumerate(groups, 1):
        what = f"[{i}/{len(groups)}]" if args.batch == 1 else f"[group {i}/{len(groups)}]"
        where = store.photo_dir(keys[group[0].name]) if args.batch == 1 else store.root
        print(f"{what} {', '.join(p.name for p in group)} -> {where}", file=sys.stderr)
        outcomes += pipeline.run([(p, keys[p.name]) for p in group], stages_until(args.until))
    record_outcomes(store, outcomes)
    print(format_run_table(outcomes, store))
    print(f"catalog: {store.catalog_dir} (`morpheus3d report --store {store.root} --out report.html`)")
    return 1 if any(o.status == "failed" for o in outcomes) else 0


def prepare(args: argparse.Namespace) -> int:
    """Prepare one photo or a folder; print the outcome table; exit 1 when any photo failed, naming
    them on stderr (``--allow-failures``: exit 0, for folders where some bad files are expected)."""
    from ops.intake.photo import LoadConfig
    from ops.intake.photo_folder import list_photos
    from ops.intake.plan import PlanConfig
    from ops.intake.prepare import PrepareConfig
    from ops.intake.segment import SegmentConfig
    from ops.pipeline.prepare_batch import failed_photos, format_table, prepare_many, print_progress

    try:
        cfg = PrepareConfig(
            load=LoadConfig(max_pixels=int(args.max_megapixels * 1e6)),
            segment=replace(SegmentConfig(use_rembg=not args.no_rembg, rembg_model=args.rembg_model),
                            **({} if args.min_confidence is None else {
                                "min_confidence": args.min_confidence,
                                "ok_confidence": max(args.min_confidence, SegmentConfig.ok_confidence)})),
            border_ratio=args.border_ratio,
        )
        plan_cfg = replace(PlanConfig(), hf_threshold=args.hf_threshold)
    except ValueError as exc:
        print(f"morpheus3d prepare: {exc}", file=sys.stderr)
        return 2
    if not 0.0 <= args.border_ratio < 0.5:
        print("morpheus3d prepare: --border-ratio must lie in [0, 0.5)", file=sys.stderr)
        return 2
    if args.photo.is_dir():
        photos, out = list_photos(args.photo), args.out
        print(f"preparing {len(photos)} photos from {args.photo} into {out}/<photo>/", file=sys.stderr)
        outcomes = prepare_many(photos, out, cfg, plan_cfg, args.force, print_progress)
    elif args.photo.exists():
        from ops.intake.segment import Segmenter
        from ops.pipeline.prepare_batch import prepare_one

        outcomes = [prepare_one(args.photo, args.out, cfg, plan_cfg, Segmenter(cfg.segment), args.force)]
    else:
        print(f"morpheus3d prepare: {args.photo}: no such file or folder", file=sys.stderr)
        return 2
    print(format_table(outcomes))
    failed = failed_photos(outcomes)
    if not failed:
        return 0
    if args.allow_failures:
        print(f"morpheus3d prepare: {len(failed)} of {len(outcomes)} photo(s) failed (allowed by --allow-failures): "
              f"{', '.join(failed)}", file=sys.stderr)
        return 0
    print(f"morpheus3d prepare: {len(failed)} of {len(outcomes)} photo(s) failed: {', '.join(failed)} (the "
          "table above says why and how to fix each; --allow-failures exits 0 when some failures are expected)",
          file=sys.stderr)
    return 1


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "doctor":
        return doctor()
    if args.command == "prepare":
        return prepare(args)
    if args.command == "run":
        return run_command(args)
    if args.command == "report":
        return report_command(args)
    parser.print_help(sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
