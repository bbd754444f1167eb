"""USDZ export of the baked asset, for iOS AR Quick Look (which reads USDZ only: no glTF, no OBJ).

What ``encode_usdz`` writes, with Pixar's ``usd-core`` (``pxr``):

* a stage with ``upAxis = "Y"``, ``metersPerUnit = 1`` and a default prim: an ``Xform`` named after the
  (sanitised) asset name, of kind ``component``. AR Quick Look places the default prim, so everything
  lives under it; the caller has already put the vertices in metres, +Y up, front facing +Z;
* ``/<name>/Geom``: a ``UsdGeom.Mesh`` of triangles with vertex-interpolated ``normals`` and
  ``primvars:st`` (``texCoord2f[]``), its ``extent``, ``subdivisionScheme = "none"`` (else renderers
  subdivide a polygon soup into a blob) and ``doubleSided = false``;
* ``/<name>/Materials/Material``: a ``UsdPreviewSurface`` — the only surface shader AR Quick Look
  knows — with ``diffuseColor`` from a ``UsdUVTexture`` that reads the packaged PNG at the ``st``
  primvar (through a ``UsdPrimvarReader_float2``); ``metallic = 0``, ``roughness = 1``: the matte
  dielectric our GLB declares too;
* the texture as ``textures/basecolor.png`` inside the package.

Texture orientation: USD puts st = (0, 0) at the *bottom-left* of the image, i.e. image row 0 is
t = 1. ``BakedTexture`` has row 0 at v = 1 with v up, so the image goes in as-is and ``st = uvs``
unchanged (no flip either way; ``tests/test_usdz_export.py`` checks colours through the st).

The package follows the USDZ rules (AR Quick Look refuses anything else): an *uncompressed* zip,
every file's data 64-byte aligned (so it can be memory-mapped), the root layer (binary ``.usdc``)
first, only USD layers and PNG/JPEG images inside, nothing referenced outside the package. USD's
own zip writer (``Sdf.ZipFileWriter``) writes it, from a layer and PNG in a temporary directory.

``check_usdz`` runs USD's own compliance checks. ``UsdUtils.ComplianceChecker(arkit=True)`` exists
up to usd-core 26.5 and is used there; from 26.8 on it is gone (``usdchecker`` moved to the
``UsdValidation`` framework, which has no ARKit profile), so there every registered validator runs,
plus the ARKit-profile rules the framework lacks (allowed prim types, shader ids and packaged file
types), re-stated here. usd-core < 26.3 is not supported: those wheels ship no UsdPreviewSurface
shader definitions, so the checker's shader rule crashes (OpenUSD#3983), and 25.5 has no
``Sdf.ZipFileWriter`` binding.
"""

from __future__ import annotations

import io
import os
import tempfile
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from morpheus_core.geometry.textured_mesh import BakedTexture
from morpheus_core.runtime.atomic_io import atomic_write_bytes

TEXTURE_NAME = "textures/basecolor.png"
"""Path of the packaged texture, relative to the root layer (and so inside the package)."""

_ZIP_MTIME = 315_619_200  # 1980-01-02 00:00 UTC: a zip date is local time from 1980, so no time zone goes below it

# ARKit profile (the old ComplianceChecker's arkit=True rules): what AR Quick Look can display.
_ARKIT_PRIM_TYPES = frozenset({
    "", "Scope", "Xform", "Camera", "Shader", "Material", "Mesh", "Sphere", "Cube", "Cylinder", "Cone",
    "Capsule", "GeomSubset", "Points", "SkelRoot", "Skeleton", "SkelAnimation", "BlendShape", "SpatialAudio",
    "PhysicsScene", "Preliminary_ReferenceImage", "Preliminary_Text", "Preliminary_Trigger",
})
_ARKIT_SHADER_IDS = frozenset({"UsdPreviewSurface", "UsdUVTexture", "UsdTransform2d"})
_ARKIT_FILE_EXTENSIONS = frozenset({"usd", "usda", "usdc", "usdz", "png", "jpg", "jpeg", "exr"})
# Validators whose warnings the ARKit profile treats as failures: AR Quick Look cannot follow a path out of the package.
_ARKIT_ERRORS = frozenset({"usdUtilsValidators:PackageEncapsulationValidator"})


def _require_usd() -> None:
    """Import USD lazily (the rest of ``morpheus_core.export`` must not pay for loading it), with a useful
    message if it is missing: it is a declared dependency, so only a broken install lands here."""
    try:
        from pxr import Sdf, Tf, Usd, UsdGeom, UsdShade, UsdUtils  # noqa: F401  (loads the native libraries)
    except ImportError as exc:
        raise ImportError(
            "USDZ export needs Pixar's USD Python bindings: pip install usd-core "
            f"(declared in pyproject.toml, but this environment cannot import it: {exc})"
        ) from exc


@dataclass(frozen=True)
class _Arrays:
    """Validated, contiguous copies of the mesh in the dtypes USD stores."""

    points: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (F, 3) int32
    st: np.ndarray  # (N, 2) float32
    normals: np.ndarray  # (N, 3) float32
    texture: np.ndarray  # (H, W, 3) uint8


def _validated(baked: BakedTexture) -> _Arrays:
    """Check ``baked`` thoroughly (USD would happily store NaNs or dangling indices) and convert it."""

    def float_array(name: str, value: Any, width: int) -> np.ndarray:
        arr = np.asarray(value)
        if arr.ndim != 2 or arr.shape[1] != width:
            raise ValueError(f"{name} must have shape (N, {width}), got {arr.shape}")
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
        if not np.isfinite(arr).all():
            bad = int((~np.isfinite(arr)).any(axis=1).sum())
            raise ValueError(f"{name} has {bad} rows with NaN or Inf")
        out = np.ascontiguousarray(arr, dtype=np.float32)
        if not np.isfinite(out).all():  # finite float64 beyond float32's range
            raise ValueError(f"{name} overflows float32")
        return out

    points = float_array("vertices", baked.vertices, 3)
    n = len(points)
    if n == 0:
        raise ValueError("empty mesh: no vertices")
    st = float_array("uvs", baked.uvs, 2)
    normals = float_array("normals", baked.normals, 3)
    for name, arr in (("uvs", st), ("normals", normals)):
        if len(arr) != n:
            raise ValueError(f"{name} has {len(arr)} rows but there are {n} vertices (all attributes are per vertex)")

    faces = np.asarray(baked.faces)
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    if len(faces) == 0:
        raise ValueError("empty mesh: no faces")
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be integers, got dtype {faces.dtype}")
    lo, hi = int(faces.min()), int(faces.max())
    if lo < 0 or hi >= n:
        raise ValueError(f"face indices must lie in [0, {n}), got range [{lo}, {hi}]")

    texture = np.asarray(baked.texture)
    if texture.dtype != np.uint8:
        raise ValueError(f"texture must be uint8, got dtype {texture.dtype}")
    if texture.ndim != 3 or texture.shape[2] != 3 or texture.shape[0] == 0 or texture.shape[1] == 0:
        raise ValueError(f"texture must have shape (H, W, 3), got {texture.shape}")

    return _Arrays(points, np.ascontiguousarray(faces, dtype=np.int32), st, normals, np.ascontiguousarray(texture))


def _prim_name(name: str) -> str:
    """A valid USD prim name from ``name`` (``"3d chair"`` → ``"_d_chair"``); empty → ``"asset"``."""
    from pxr import Tf

    return Tf.MakeValidIdentifier(name) if name else "asset"


def _png_bytes(texture: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(texture).save(buf, format="PNG")  # uint8 HxWx3: RGB
    return buf.getvalue()


def _author_stage(layer_path: Path, arrays: _Arrays, prim_name: str) -> None:
    """Write the root layer (``.usdc``) next to ``TEXTURE_NAME``."""
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdShade, Vt

    stage = Usd.Stage.CreateNew(str(layer_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)

    root = UsdGeom.Xform.Define(stage, Sdf.Path.absoluteRootPath.AppendChild(prim_name))
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)  # a referenceable model, not a set

    mesh = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild("Geom"))
    points = Vt.Vec3fArray.FromNumpy(arrays.points)
    mesh.CreatePointsAttr(points)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(arrays.faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(arrays.faces.reshape(-1)))
    mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(arrays.normals))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    # Counter-clockwise front faces (glTF's and our convention) = USD's default rightHanded; say so.
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateDoubleSidedAttr(False)
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set(Vt.Vec2fArray.FromNumpy(arrays.st))

    looks = UsdGeom.Scope.Define(stage, root.GetPath().AppendChild("Materials"))
    material = UsdShade.Material.Define(stage, looks.GetPath().AppendChild("Material"))
    surface = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("PreviewSurface"))
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")

    reader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("STReader"))
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)

    texture = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("BaseColorTexture"))
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(TEXTURE_NAME))
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    # The bake is an sRGB image; a UV atlas must not wrap (bilinear taps at u≈0 would read u≈1).
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    texture.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0.5, 0.5, 0.5, 1.0))
    rgb = texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(rgb)

    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()


def encode_usdz(baked: BakedTexture, name: str = "asset") -> bytes:
    """The baked asset as USDZ package bytes (see the module docstring for the layout).

    Raises ``ValueError`` on bad input (NaN/Inf, face indices out of range, an empty mesh, a texture
    that is not uint8 HxWx3) and ``RuntimeError`` if USD fails to write the package."""
    arrays = _validated(baked)
    _require_usd()
    from pxr import Sdf

    prim_name = _prim_name(name)
    png = _png_bytes(arrays.texture)
    with tempfile.TemporaryDirectory(prefix="morpheus-usdz-") as tmp:
        tmp_dir = Path(tmp)
        (tmp_dir / TEXTURE_NAME).parent.mkdir(parents=True)
        (tmp_dir / TEXTURE_NAME).write_bytes(png)
        layer_path = tmp_dir / f"{prim_name}.usdc"
        _author_stage(layer_path, arrays, prim_name)
        usdz_path = tmp_dir / f"{prim_name}.usdz"
        # The zip writer stamps each entry with its file's modification time: a fixed one makes the package's
        # bytes a function of the asset alone (the same run gives the same file, and its hash in the manifest).
        for written in (layer_path, tmp_dir / TEXTURE_NAME):
            os.utime(written, (_ZIP_MTIME, _ZIP_MTIME))
        # USD's zip writer stores (never compresses) and pads every file's data to 64 bytes.
        # UsdUtils.CreateNewARKitUsdzPackage would do too, but it renames the texture to "0/basecolor.png";
        # our layer is already one self-contained usdc, so writing the two files ourselves keeps the layout.
        writer = Sdf.ZipFileWriter.CreateNew(str(usdz_path))
        writer.AddFile(str(layer_path), layer_path.name)  # first: a USDZ's root layer is its first file
        writer.AddFile(str(tmp_dir / TEXTURE_NAME), TEXTURE_NAME)
        if not writer.Save():
            raise RuntimeError(f"Sdf.ZipFileWriter failed to write {usdz_path}")
        return usdz_path.read_bytes()


def export_usdz(baked: BakedTexture, path: Path | str, name: str = "asset") -> Path:
    """Write ``encode_usdz(baked, name)`` to ``path`` atomically: a failure leaves the old file (or none)."""
    data = encode_usdz(baked, name)  # raises before anything touches ``path``
    return atomic_write_bytes(Path(path), data)


_COMPLIANCE_CHECKER = "UsdUtils.ComplianceChecker(arkit=True)"
_FRAMEWORK = "UsdValidation + ARKit rules"


@dataclass(frozen=True)
class UsdzCheck:
    """What the compliance checks said about a package. ``ok`` ⇔ no errors; warnings are advisory."""

    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    checker: str = ""
    """Which checker ran: ``_COMPLIANCE_CHECKER`` (usd-core <= 26.5) or ``_FRAMEWORK`` (26.8+)."""

    @property
    def ok(self) -> bool:
        return not self.errors


def check_usdz(path: Path | str) -> UsdzCheck:
    """Run USD's compliance checks (ARKit profile) on the package at ``path``.

    ``errors`` holds the checker's errors and failed checks (empty ⇔ compliant), ``warnings`` its
    advisories. Raises ``FileNotFoundError`` if there is no file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(path)
    _require_usd()
    from pxr import UsdUtils

    if hasattr(UsdUtils, "ComplianceChecker"):  # usd-core <= 26.5
        with warnings.catch_warnings():
            # Deprecated in 26.x in favour of UsdValidation, which still lacks the ARKit rules.
            warnings.simplefilter("ignore", DeprecationWarning)
            checker = UsdUtils.ComplianceChecker(arkit=True, skipVariants=False, rootPackageOnly=False)
        checker.CheckCompliance(str(path))
        return UsdzCheck(
            errors=[*checker.GetErrors(), *checker.GetFailedChecks()],
            warnings=list(checker.GetWarnings()),
            checker=_COMPLIANCE_CHECKER,
        )
    from pxr import Tf, Usd

    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:  # e.g. a compressed root layer: USD refuses to read it at all
        stage = None
        reason = str(exc).strip()
    else:
        reason = "Usd.Stage.Open returned None"
    if stage is None:
        return UsdzCheck(errors=[f"Failed to open USD stage from {path}: {reason}"], checker=_FRAMEWORK)
    errors, warns = _validation_framework(stage)
    errors += _arkit_rules(path, stage)
    return UsdzCheck(errors=errors, warnings=warns, checker=_FRAMEWORK)


def _validation_framework(stage: Any) -> tuple[list[str], list[str]]:
    """All registered ``UsdValidation`` validators, as ``usdchecker`` (26.8+) runs them."""
    from pxr import UsdValidation

    context = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors: list[str] = []
    warns: list[str] = []
    for err in context.Validate(stage):
        if err.HasNoError():
            continue
        validator = err.GetValidator().GetMetadata().name
        text = f"{err.GetErrorAsString()} (validator {validator})"
        fatal = err.GetType() == UsdValidation.ValidationErrorType.Error or validator in _ARKIT_ERRORS
        (errors if fatal else warns).append(text)
    return errors, warns


def _arkit_rules(path: Path, stage: Any) -> list[str]:
    """The ARKit-profile rules that ``UsdValidation`` (26.8+) does not carry: prim types AR Quick Look can
    display, shaders it implements, file types it can read inside the package."""
    from pxr import Usd, UsdShade

    failures: list[str] = []
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
    for name in names:
        ext = name.rsplit(".", 1)[-1].lower() if "." in name else ""
        if ext not in _ARKIT_FILE_EXTENSIONS:
            failures.append(f"File '{name}' in the package has an unsupported extension '{ext}' (ARKit)")

    for prim in stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimAllPrimsPredicate)):
        type_name = str(prim.GetTypeName())
        if type_name not in _ARKIT_PRIM_TYPES and not type_name.startswith("RealityKit"):
            failures.append(f"Prim <{prim.GetPath()}> has type '{type_name}', unsupported by ARKit")
        if not prim.IsA(UsdShade.Shader):
            continue
        shader = UsdShade.Shader(prim)
        if shader.GetImplementationSource() != UsdShade.Tokens.id:
            failures.append(f"Shader <{prim.GetPath()}> has implementation source "
                            f"'{shader.GetImplementationSource()}', not 'id' (ARKit)")
        shader_id = str(shader.GetShaderId() or "")
        if not (shader_id in _ARKIT_SHADER_IDS or shader_id.startswith(("UsdPrimvarReader", "ND_"))):
            failures.append(f"Shader <{prim.GetPath()}> has id '{shader_id}', unsupported by ARKit")
    return failures
