"""Regular tetrahedral grid for DMTet: a cube grid with every cube split into 6 Kuhn tetrahedra.

The cube with corners {0,1}³ is split along its main diagonal 000→111 into the six monotone
lattice paths from 000 to 111, one per ordering of the axes: tet(p) = (000, e_p0, e_p0+e_p1, 111).
Every cube uses the same split (the Freudenthal triangulation), so a square face shared by two
cubes is cut along the same diagonal from both sides — the diagonal through the face's corners
with the smallest and the largest coordinate sum — and the tetrahedralisation is conforming.
Edges of the grid are exactly the lattice steps by a non-zero 0/1 offset (3 axis steps, 3 face
diagonals, 1 main diagonal: 7 per vertex), so they are generated directly, never deduplicated.

Vertex (i, j, k) — i along x, j along y, k along z — has index (i·(n+1) + j)·(n+1) + k and
sits at −h + 2h·(i, j, k)/n for a grid spanning [−h, h]³ (h = ``half_extent``).

The topology depends on the resolution only, so it is cached on disk per resolution under
``$MORPHEUS_CACHE/tets`` (default ``~/.cache/morpheus3d/tets``). Files are written to a temporary
sibling and renamed into place; a file that is truncated, corrupt, of the wrong version or of
the wrong shape is detected on load, reported with a warning and rebuilt. Measured on the 2-core
CPU: building takes ~0.05 s at n = 64 and ~0.2–0.3 s at n = 128 (12.6M tets), and a validated cache
load costs about the same (~0.06 s / ~0.3 s; 40 MB / 320 MB files): the cache saves little on this
machine. It is kept because the design asks for per-resolution caching and its validation is cheap;
``use_cache=False`` skips the disk entirely.
"""

from __future__ import annotations

import itertools
import os
import tempfile
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CACHE_ENV = "MORPHEUS_CACHE"
CACHE_FORMAT_VERSION = 1
# Index arrays are stored as int32 on disk (half the size; 2^31 vertices is resolution ~1290)
# and widened to int64 in memory, the dtype torch indexing wants.
_DISK_INDEX_DTYPE = np.int32
_MAX_RESOLUTION = 1024
# Rows of tets/edges that a cache load recomputes and compares (beyond the zip CRC).
_SPOT_CHECK_ROWS = 4096


def _kuhn_offsets() -> np.ndarray:
    """(6, 4, 3) corner offsets of the six Kuhn tets of the unit cube, all positively oriented."""
    tets = []
    for perm in itertools.permutations(range(3)):
        corners = [np.zeros(3, dtype=np.int64)]
        for axis in perm:
            step = corners[-1].copy()
            step[axis] = 1
            corners.append(step)
        c = np.stack(corners)
        # det(e_p0, e_p0+e_p1, 111) is the sign of the permutation: odd ones swap two corners.
        if np.linalg.det((c[1:] - c[0]).astype(np.float64)) < 0:
            c[[2, 3]] = c[[3, 2]]
        tets.append(c)
    return np.stack(tets)


KUHN_OFFSETS = _kuhn_offsets()
# The 7 edge directions of the Freudenthal triangulation: every non-zero 0/1 offset.
EDGE_OFFSETS = np.array([d for d in itertools.product((0, 1), repeat=3) if any(d)], dtype=np.int64)


def _check_resolution(resolution: int) -> int:
    if isinstance(resolution, bool) or not isinstance(resolution, (int, np.integer)):
        raise TypeError(f"tet grid resolution must be an int, got {type(resolution).__name__}")
    if not 1 <= int(resolution) <= _MAX_RESOLUTION:
        raise ValueError(f"tet grid resolution must be in [1, {_MAX_RESOLUTION}], got {resolution}")
    return int(resolution)


def num_grid_vertices(resolution: int) -> int:
    return (resolution + 1) ** 3


def num_grid_edges(resolution: int) -> int:
    n = resolution
    return int(sum(np.prod([n + 1 - d for d in off]) for off in EDGE_OFFSETS))


def _strides(resolution: int) -> np.ndarray:
    m = resolution + 1
    return np.array([m * m, m, 1], dtype=np.int64)


def grid_points(resolution: int, half_extent: float = 1.0) -> np.ndarray:
    """(N, 3) float32 vertex positions of the grid spanning [−half_extent, half_extent]³."""
    n = _check_resolution(resolution)
    if not (np.isfinite(half_extent) and half_extent > 0):
        raise ValueError(f"half_extent must be a positive finite number, got {half_extent}")
    ticks = np.linspace(-half_extent, half_extent, n + 1, dtype=np.float64)
    x, y, z = np.meshgrid(ticks, ticks, ticks, indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=-1).astype(np.float32)


def boundary_mask(resolution: int) -> np.ndarray:
    """(N,) bool: vertices on the faces of the grid's box."""
    n = _check_resolution(resolution)
    ijk = np.indices((n + 1,) * 3).reshape(3, -1)
    return ((ijk == 0) | (ijk == n)).any(axis=0)


def _tets_of_cubes(resolution: int, cubes: np.ndarray) -> np.ndarray:
    """(len(cubes)·6, 4) int64 tets of the given flat cube indices (cube c = (i·n + j)·n + k)."""
    n = resolution
    i, rem = np.divmod(cubes, n * n)
    j, k = np.divmod(rem, n)
    strides = _strides(n)
    base = i * strides[0] + j * strides[1] + k
    corner = KUHN_OFFSETS @ strides  # (6, 4) index offsets of the corners
    return (base[:, None, None] + corner[None]).reshape(-1, 4)


def _edges_along(resolution: int, offset: np.ndarray) -> np.ndarray:
    """(E_d, 2) int64 edges (v, v + offset) for every v whose neighbour stays in the grid."""
    n = resolution
    lo = [np.arange(n + 1 - int(d), dtype=np.int64) for d in offset]
    strides = _strides(n)
    start = (lo[0][:, None, None] * strides[0] + lo[1][None, :, None] * strides[1] + lo[2][None, None, :]).ravel()
    return np.stack([start, start + int(offset @ strides)], axis=-1)


def build_topology(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Uncached: (tets (6n³, 4) int64, edges (E, 2) int64 with edges[:, 0] < edges[:, 1])."""
    n = _check_resolution(resolution)
    tets = _tets_of_cubes(n, np.arange(n**3, dtype=np.int64))
    edges = np.concatenate([_edges_along(n, off) for off in EDGE_OFFSETS])
    return tets, edges


@dataclass(frozen=True, eq=False)
class TetGrid:
    """Vertices (N, 3) float32 in [−half_extent, half_extent]³, tets (T, 4) int64 positively
    oriented, edges (E, 2) int64 unique with i < j, boundary (N,) bool."""

    resolution: int
    half_extent: float
    vertices: np.ndarray
    tets: np.ndarray
    edges: np.ndarray
    boundary: np.ndarray

    @property
    def cell_size(self) -> float:
        return 2.0 * self.half_extent / self.resolution


def default_cache_dir() -> Path:
    root = os.environ.get(CACHE_ENV)
    base = Path(root).expanduser() if root else Path.home() / ".cache" / "morpheus3d"
    return base / "tets"


def cache_path(resolution: int, cache_dir: Path | str | None = None) -> Path:
    folder = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    return folder / f"kuhn_tets_{_check_resolution(resolution)}_v{CACHE_FORMAT_VERSION}.npz"


class TetCacheError(ValueError):
    """A cached tet grid failed validation (it is rebuilt, never used)."""


def _spot_rows(total: int, count: int, seed: int) -> np.ndarray:
    # First and last rows plus a seeded random sample: corruption at either end (the usual
    # truncation/partial-write shapes) and anywhere in between is compared with the formula.
    if total <= count:
        return np.arange(total)
    picks = np.random.default_rng(seed).integers(0, total, size=count)
    return np.unique(np.concatenate([picks, [0, total - 1]]))


def _validate(resolution: int, data: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    n = resolution
    for name in ("version", "resolution", "tets", "edges"):
        if name not in data:
            raise TetCacheError(f"missing array {name!r}")
    if int(data["version"]) != CACHE_FORMAT_VERSION or int(data["resolution"]) != n:
        raise TetCacheError(f"version/resolution {int(data['version'])}/{int(data['resolution'])}, want "
                            f"{CACHE_FORMAT_VERSION}/{n}")
    tets, edges = data["tets"], data["edges"]
    want = {"tets": (6 * n**3, 4), "edges": (num_grid_edges(n), 2)}
    for name, arr in (("tets", tets), ("edges", edges)):
        if arr.dtype != _DISK_INDEX_DTYPE or arr.shape != want[name]:
            raise TetCacheError(f"{name}: {arr.dtype} {arr.shape}, want {np.dtype(_DISK_INDEX_DTYPE)} {want[name]}")
        if arr.min() < 0 or arr.max() >= num_grid_vertices(n):
            raise TetCacheError(f"{name}: index outside [0, {num_grid_vertices(n)})")
    if not (edges[:, 0] < edges[:, 1]).all():
        raise TetCacheError("edges are not ordered i < j")
    cubes = _spot_rows(n**3, _SPOT_CHECK_ROWS, seed=n)
    expect = _tets_of_cubes(n, cubes).reshape(-1, 6, 4)
    if not np.array_equal(tets.reshape(-1, 6, 4)[cubes], expect):
        raise TetCacheError("tets differ from the Kuhn split")
    rows = _spot_rows(len(edges), _SPOT_CHECK_ROWS, seed=n + 1)
    if not np.array_equal(edges[rows], _edge_rows(n, rows)):
        raise TetCacheError("edges differ from the grid's edge list")
    return tets.astype(np.int64), edges.astype(np.int64)


def _edge_rows(resolution: int, rows: np.ndarray) -> np.ndarray:
    """edges[rows] of the full edge list (directions in ``EDGE_OFFSETS`` order), computed directly."""
    n = resolution
    strides = _strides(n)
    out = np.empty((len(rows), 2), dtype=np.int64)
    start = 0
    for off in EDGE_OFFSETS:
        shape = tuple(n + 1 - int(d) for d in off)
        count = int(np.prod(shape))
        sel = (rows >= start) & (rows < start + count)
        i, j, k = np.unravel_index(rows[sel] - start, shape)
        first = i * strides[0] + j * strides[1] + k
        out[sel] = np.stack([first, first + int(off @ strides)], axis=-1)
        start += count
    return out


def _load(path: Path, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    # The zip container checks each member's CRC-32 as it is read: a flipped byte anywhere in
    # the arrays raises here; truncation breaks the central directory. Both count as invalid.
    with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as npz:  # our handle: closed even on failure
        data = {name: npz[name] for name in npz.files}
    return _validate(resolution, data)


def _save_atomic(path: Path, resolution: int, tets: np.ndarray, edges: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, version=np.int64(CACHE_FORMAT_VERSION), resolution=np.int64(resolution),
                     tets=tets.astype(_DISK_INDEX_DTYPE), edges=edges.astype(_DISK_INDEX_DTYPE))
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes it private; the cache is shareable
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load_or_build_topology(resolution: int, cache_dir: Path | str | None = None,
                           use_cache: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(tets, edges) int64 for ``resolution``: from the disk cache when valid, else built (and cached)."""
    n = _check_resolution(resolution)
    if not use_cache:
        return build_topology(n)
    path = cache_path(n, cache_dir)
    if path.exists():
        try:
            return _load(path, n)
        except (OSError, ValueError, TypeError, EOFError, KeyError, zipfile.BadZipFile) as exc:
            warnings.warn(f"tet grid cache {path} is invalid ({exc}); rebuilding it", RuntimeWarning, stacklevel=2)
    tets, edges = build_topology(n)
    try:
        _save_atomic(path, n, tets, edges)
    except OSError as exc:  # a read-only cache folder must not stop the pipeline
        warnings.warn(f"could not write tet grid cache {path}: {exc}", RuntimeWarning, stacklevel=2)
    return tets, edges


def tet_grid(resolution: int, half_extent: float = 1.0, *, cache_dir: Path | str | None = None,
             use_cache: bool = True) -> TetGrid:
    """The Kuhn tet grid of ``resolution`` cubes per axis spanning [−half_extent, half_extent]³."""
    n = _check_resolution(resolution)
    vertices = grid_points(n, half_extent)
    tets, edges = load_or_build_topology(n, cache_dir, use_cache)
    return TetGrid(n, float(half_extent), vertices, tets, edges, boundary_mask(n))
