"""The ``morpheus3d`` command line. Subcommands grow with the pipeline; none imports Dagster."""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata as md
import platform
import sys
from collections.abc import Sequence

from morpheus_core.priors.registry import PRIOR_MODELS, ModelRegistry, rembg_model_file

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
    print("\nStatus:", "OK" if ok else "BROKEN INSTALL (see above)")
    return 0 if ok else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="morpheus3d", description="Product photos to textured 3D assets.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.add_parser("doctor", help="check the installation, CUDA, OpenCV build and model folders")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "doctor":
        return doctor()
    parser.print_help(sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
