"""Mesh hygiene before UV baking: connected components, floater removal, topology numbers.

DMTet surfaces share their vertices between faces, so connectivity is by vertex index (no welding
by position; ``metrics.mesh_health`` welds, because UV seams split the exported vertices). Two
faces are connected when they share an edge — a pair of surfaces touching at one vertex stays two
components, since unwrapping and floater removal treat them as separate pieces.

A mesh without faces is not an error here: every function returns a well-defined empty result
(no components, zero counts, genus None) and the caller decides; ``export.uv_bake.bake_uv`` refuses it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from morpheus_core.geometry.mesh import Mesh


def connected_labels(n: int, pairs: np.ndarray) -> np.ndarray:
    """Component label (0…k−1, in order of each component's smallest node) of ``n`` nodes joined by
    ``pairs`` (P, 2). Union–find by hooking roots onto the smaller root and pointer jumping, all
    vectorised: a Python loop per node would take seconds on a 50k-face mesh."""
    parent = np.arange(n, dtype=np.int64)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if n == 0:
        return parent
    while True:
        ra, rb = parent[pairs[:, 0]], parent[pairs[:, 1]]
        differ = ra != rb
        if not differ.any():
            break
        lo, hi = np.minimum(ra[differ], rb[differ]), np.maximum(ra[differ], rb[differ])
        np.minimum.at(parent, hi, lo)
        while True:  # shortcut every node to its root, so the next round hooks roots only
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
    return np.unique(parent, return_inverse=True)[1].reshape(-1)


def _edge_keys(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """(3F,) undirected edge key min·V + max of edge k of face f, at position 3f + k."""
    a, b = faces, np.roll(faces, -1, axis=1)
    return (np.minimum(a, b) * num_vertices + np.maximum(a, b)).reshape(-1)


def _arrays(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    return (mesh.vertices.detach().cpu().double().numpy(), mesh.faces.detach().cpu().numpy())


def face_areas(mesh: Mesh) -> np.ndarray:
    """(F,) float64 triangle areas."""
    verts, faces = _arrays(mesh)
    c = verts[faces]
    return 0.5 * np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)


def mesh_components(mesh: Mesh) -> tuple[Tensor, Tensor]:
    """Per-face component labels (F,) int64 and per-component surface area (K,) float64.

    Label 0 is the largest component by area (ties broken by lowest face index), so callers can
    keep "the main part" without sorting again."""
    _, faces = _arrays(mesh)
    nf = len(faces)
    if nf == 0:
        return torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.float64)
    keys = _edge_keys(faces, mesh.num_vertices)
    order = np.argsort(keys, kind="stable")
    same = keys[order][1:] == keys[order][:-1]
    # Faces listed consecutively under one edge key share that edge (a chain covers non-manifold edges too).
    face_of = order // 3
    labels = connected_labels(nf, np.stack([face_of[:-1][same], face_of[1:][same]], axis=1))
    areas = np.bincount(labels, weights=face_areas(mesh), minlength=int(labels.max()) + 1)
    rank = np.lexsort((np.arange(len(areas)), -areas))  # by area, descending; stable on the label
    relabel = np.empty_like(rank)
    relabel[rank] = np.arange(len(rank))
    return torch.from_numpy(relabel[labels]), torch.from_numpy(areas[rank])


def compact(mesh: Mesh, keep_faces: Tensor) -> Mesh:
    """The faces selected by the boolean ``keep_faces`` (F,), with only the vertices they use, in
    their original order (so a mesh with nothing dropped comes back identical)."""
    faces = mesh.faces[keep_faces.to(mesh.faces.device)]
    used = torch.zeros(mesh.num_vertices, dtype=torch.bool, device=mesh.faces.device)
    used[faces.reshape(-1)] = True
    new_index = torch.cumsum(used.long(), 0) - 1
    return Mesh(mesh.vertices[used.to(mesh.vertices.device)], new_index[faces])


def drop_floaters(mesh: Mesh, min_share: float) -> tuple[Mesh, dict[str, Any]]:
    """Remove components whose surface area is below ``min_share`` of the total; the largest
    component always stays (a mesh of many equal crumbs keeps one). Vertices are compacted.

    Report: ``components_before``, ``components`` (after), ``floaters_dropped`` and
    ``floater_area_share`` (their summed area over the total area; 0.0 for a zero-area mesh)."""
    if not 0.0 <= min_share < 1.0:
        raise ValueError(f"min_share must lie in [0, 1), got {min_share}")
    labels, areas = mesh_components(mesh)
    total = float(areas.sum())
    keep_component = areas >= min_share * total
    if len(areas):
        keep_component[0] = True
    dropped = int((~keep_component).sum())
    report: dict[str, Any] = {
        "components_before": len(areas), "components": len(areas) - dropped, "floaters_dropped": dropped,
        "floater_area_share": round(float(areas[~keep_component].sum()) / total, 6) if total > 0 else 0.0,
    }
    if dropped == 0:
        return mesh, report
    return compact(mesh, keep_component[labels]), report


def topology_report(mesh: Mesh) -> dict[str, Any]:
    """Components, Euler number and genus, non-manifold edges, boundary edges and holes.

    * ``euler_number``: V − E + F over the vertices faces use (stray points do not shift it);
    * ``genus``: Σ over components of (2 − χ_c)/2, when every component is closed (each edge has
      exactly two faces); None when the mesh has boundary or non-manifold edges (no genus
      exists then) or no faces. χ_c counts the vertices of component c, so components touching at
      a vertex each count it;
    * ``non_manifold_edges``: edges with more than two faces; ``boundary_edges``: edges with one;
    * ``holes``: connected loops of boundary edges (two holes pinched at one vertex count once).
    """
    _, faces = _arrays(mesh)
    nv, nf = mesh.num_vertices, len(faces)
    report: dict[str, Any] = {"components": 0, "euler_number": 0, "genus": None, "non_manifold_edges": 0,
                              "boundary_edges": 0, "holes": 0}
    if nf == 0:
        return report
    labels_t, _ = mesh_components(mesh)
    labels = labels_t.numpy()
    k = int(labels.max()) + 1
    keys = _edge_keys(faces, nv)
    edge_keys, edge_index, counts = np.unique(keys, return_inverse=True, return_counts=True)
    edge_index = edge_index.reshape(-1)
    used = np.unique(faces)
    report.update({"components": k, "euler_number": int(len(used) - len(edge_keys) + nf),
                   "non_manifold_edges": int((counts > 2).sum()), "boundary_edges": int((counts == 1).sum())})

    boundary = edge_keys[counts == 1]
    if len(boundary):
        ends = np.stack([boundary // nv, boundary % nv], axis=1)
        nodes, local = np.unique(ends, return_inverse=True)
        report["holes"] = int(connected_labels(len(nodes), local.reshape(-1, 2)).max()) + 1
    if report["boundary_edges"] or report["non_manifold_edges"]:
        return report

    face_label = np.repeat(labels, 3)  # the label of every (face, corner) slot, aligned with ``keys``
    edges_per = np.bincount(face_label[np.unique(edge_index, return_index=True)[1]], minlength=k)
    faces_per = np.bincount(labels, minlength=k)
    verts_per = np.bincount(np.unique(np.stack([np.repeat(labels, 3), faces.reshape(-1)], 1), axis=0)[:, 0],
                            minlength=k)
    chi = verts_per - edges_per + faces_per
    twice = int((2 - chi).sum())
    report["genus"] = twice // 2 if twice % 2 == 0 else twice / 2  # odd: a non-orientable piece
    return report
