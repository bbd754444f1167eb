"""Kuhn tet grid: counts, orientation, volume, conformity, edge list, disk cache and its recovery."""

from __future__ import annotations

import os
import warnings
import zipfile
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from morpheus_core.geometry import tets as T


def _signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = vertices.astype(np.float64)[tets]
    return np.linalg.det(p[:, 1:] - p[:, :1]) / 6.0


@pytest.mark.parametrize("n", [1, 2, 5])
def test_counts_orientation_and_volume(n: int, tmp_path: Path) -> None:
    half = 0.8
    g = T.tet_grid(n, half, cache_dir=tmp_path)
    assert g.vertices.dtype == np.float32 and g.vertices.shape == ((n + 1) ** 3, 3)
    assert g.tets.dtype == np.int64 and g.tets.shape == (6 * n**3, 4)
    assert g.edges.dtype == np.int64 and g.edges.shape == (T.num_grid_edges(n), 2)
    assert g.vertices.min() == -half and g.vertices.max() == half
    vol = _signed_volumes(g.vertices, g.tets)
    cell = (2 * half / n) ** 3
    # Every Kuhn tet of a cube has volume cell/6, all positively oriented, filling the box exactly.
    np.testing.assert_allclose(vol, cell / 6, rtol=1e-5)
    np.testing.assert_allclose(vol.sum(), (2 * half) ** 3, rtol=1e-6)
    assert g.boundary.sum() == (n + 1) ** 3 - max(n - 1, 0) ** 3


@pytest.mark.parametrize("n", [1, 3, 6])
def test_conforming_faces(n: int) -> None:
    tets, _ = T.build_topology(n)
    faces = np.concatenate([np.sort(tets[:, [a, b, c]], axis=1) for a, b, c in
                            ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))])
    _, counts = np.unique(faces, axis=0, return_counts=True)
    # Conforming: every triangle is shared by two tets, except the box's 6·2n² boundary triangles.
    assert set(counts.tolist()) <= {1, 2}
    assert (counts == 1).sum() == 6 * 2 * n * n
    verts = T.grid_points(n)
    single = np.unique(faces, axis=0, return_counts=True)
    on_box = np.abs(verts[single[0][single[1] == 1]])
    assert (np.isclose(on_box, 1.0).all(axis=1)).any(axis=1).all()


@pytest.mark.parametrize("n", [1, 4, 7])
def test_edges_are_exactly_the_tet_edges(n: int) -> None:
    tets, edges = T.build_topology(n)
    pairs = np.concatenate([tets[:, [a, b]] for a in range(4) for b in range(a + 1, 4)])
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    assert (edges[:, 0] < edges[:, 1]).all()
    assert len(np.unique(edges, axis=0)) == len(edges)
    np.testing.assert_array_equal(np.unique(edges, axis=0), pairs)
    # 7 directions per vertex: the interior vertex degree of the Freudenthal triangulation is 14.
    degree = Counter(edges.ravel().tolist())
    interior = [v for v in range(len(T.grid_points(n))) if not T.boundary_mask(n)[v]]
    assert all(degree[v] == 14 for v in interior)


def test_cache_round_trip_and_env_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(T.CACHE_ENV, str(tmp_path / "root"))
    assert T.default_cache_dir() == tmp_path / "root" / "tets"
    first = T.tet_grid(5)
    path = T.cache_path(5)
    assert path.exists() and path.parent == tmp_path / "root" / "tets"
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporaries left behind

    def no_build(_: int):
        raise AssertionError("a valid cache must be loaded, not rebuilt")

    monkeypatch.setattr(T, "build_topology", no_build)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = T.tet_grid(5)
    np.testing.assert_array_equal(first.tets, second.tets)
    np.testing.assert_array_equal(first.edges, second.edges)
    assert second.tets.dtype == np.int64


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _flip_middle_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def _resave(**changes):
    def corrupt(path: Path) -> None:
        with np.load(path) as npz:
            arrays = {k: npz[k] for k in npz.files}
        arrays.update({k: v(arrays) for k, v in changes.items()})
        with open(path, "wb") as fh:
            np.savez(fh, **arrays)

    return corrupt


def _swap_row(a):
    t = a["tets"].copy()
    t[7, [0, 1]] = t[7, [1, 0]]  # same indices, inverted orientation: only a content check sees it
    return t


CORRUPTIONS = {
    "truncated": _truncate,
    "garbage": lambda p: p.write_bytes(b"not a zip at all"),
    "empty": lambda p: p.write_bytes(b""),
    "flipped_byte": _flip_middle_byte,
    "wrong_version": _resave(version=lambda a: np.int64(99)),
    "version_not_scalar": _resave(version=lambda a: np.arange(3)),
    "wrong_resolution": _resave(resolution=lambda a: np.int64(3)),
    "wrong_dtype": _resave(tets=lambda a: a["tets"].astype(np.float32)),
    "wrong_shape": _resave(tets=lambda a: a["tets"][:-6]),
    "out_of_range": _resave(edges=lambda a: a["edges"] + 1000),
    "missing_array": lambda p: _resave()(p) or _drop_edges(p),
    "swapped_corners": _resave(tets=_swap_row),
    "shifted_edges": _resave(edges=lambda a: np.roll(a["edges"], 1, axis=0)),
}


def _drop_edges(path: Path) -> None:
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "edges"}
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


@pytest.mark.parametrize("kind", sorted(CORRUPTIONS))
def test_corrupt_cache_is_detected_and_rebuilt(kind: str, tmp_path: Path) -> None:
    n = 4
    good_tets, good_edges = T.build_topology(n)
    T.tet_grid(n, cache_dir=tmp_path)
    path = T.cache_path(n, tmp_path)
    CORRUPTIONS[kind](path)
    with pytest.warns(RuntimeWarning, match="invalid"):
        g = T.tet_grid(n, cache_dir=tmp_path)
    np.testing.assert_array_equal(g.tets, good_tets)
    np.testing.assert_array_equal(g.edges, good_edges)
    # The rebuilt file replaced the corrupt one and is valid again.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tets, edges = T.load_or_build_topology(n, tmp_path)
    np.testing.assert_array_equal(tets, good_tets)
    np.testing.assert_array_equal(edges, good_edges)
    assert zipfile.is_zipfile(path)


def test_failed_write_leaves_no_partial_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.warns(RuntimeWarning, match="could not write"):
        g = T.tet_grid(3, cache_dir=tmp_path)
    assert g.tets.shape == (6 * 27, 4)
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]  # the temporary was removed


def test_no_cache_mode_does_not_touch_disk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(T.CACHE_ENV, str(tmp_path))
    g = T.tet_grid(2, use_cache=False)
    assert g.tets.shape == (48, 4) and not any(tmp_path.iterdir())


@pytest.mark.parametrize("bad", [0, -3, 1025, 2.0, True, "8"])
def test_bad_resolution_is_rejected(bad) -> None:
    with pytest.raises((ValueError, TypeError)):
        T.tet_grid(bad, use_cache=False)


@pytest.mark.parametrize("half", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_extent_is_rejected(half: float) -> None:
    with pytest.raises(ValueError, match="half_extent"):
        T.tet_grid(2, half, use_cache=False)
