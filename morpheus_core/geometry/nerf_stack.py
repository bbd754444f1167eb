"""Several objects' NeRF fields queried together: one hash-grid launch for every object's points.

A batch of photos fits one field per object. Queried one by one, each object's render pays its own
few hundred small launches, and at 8 objects per batch the NeRF step waits for the host (H200:
894 ms a step against 454 ms of GPU work, ``benchmarks/results/field_graphs_h200.md``). A
``FieldStack`` takes the points of all objects, sorted by object, with each point's object index:
the hash-grid encode of all of them is one launch (``encode_stacked``), and only the small MLPs
run per object. Every object keeps its own parameters, so its gradients are the ones its own query
would give.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from morpheus_core.geometry.field_heads import evaluate_heads
from morpheus_core.geometry.hashgrid import encode_stacked
from morpheus_core.geometry.nerf import FieldSample, NerfField, central_difference_normals, trunc_exp


class FieldStack:
    """K ``NerfField`` of one config, queried at points of all of them at once."""

    def __init__(self, fields: Sequence[NerfField]) -> None:
        if not fields:
            raise ValueError("a field stack needs at least one field")
        if any(f.config != fields[0].config for f in fields):
            raise ValueError("stacked fields must share one NerfConfig")
        self.fields = list(fields)
        self.config = fields[0].config
        self.bbox_radius = self.config.bbox_radius

    def __len__(self) -> int:
        return len(self.fields)

    def _heads(self, feats: Tensor, counts: Sequence[int], with_albedo: bool) -> tuple[Tensor, Tensor | None]:
        """Each object's raw density (and albedo) from its own heads, concatenated in point order."""
        parts = [(f, x) for f, x in zip(self.fields, feats.split(list(counts)), strict=True) if len(x)]
        if not parts:  # no points at all: the first field's heads on the empty input, for the shapes
            parts = [(self.fields[0], feats)]
        outs = [evaluate_heads(x, f.density_mlp, f.albedo_mlp if with_albedo else None) for f, x in parts]
        density = torch.cat([d for d, _ in outs])
        return density, (torch.cat([a for _, a in outs]) if with_albedo else None)  # type: ignore[misc]

    def _features(self, points: Tensor, obj: Tensor) -> Tensor:
        return encode_stacked([f.encoding for f in self.fields], (points / self.bbox_radius + 1) * 0.5, obj)

    def _density(self, points: Tensor, raw: Tensor) -> Tensor:
        return trunc_exp(raw.squeeze(-1).float() + self.fields[0]._blob(points).float())

    def density(self, points: Tensor, obj: Tensor, counts: Sequence[int]) -> Tensor:
        """(N,) densities at ``points`` (N, 3): the first ``counts[0]`` points are object 0's, and so on;
        ``obj`` (N,) holds each point's object index (the same information, on the device). Objects
        with no points here cost nothing."""
        self._check(points, obj, counts)
        raw, _ = self._heads(self._features(points, obj), counts, False)
        return self._density(points, raw)

    def query(self, points: Tensor, obj: Tensor, counts: Sequence[int], with_normals: bool = False) -> FieldSample:
        """``NerfField.query`` of each point's own field (points sorted by object, as ``density``)."""
        self._check(points, obj, counts)
        raw, raw_albedo = self._heads(self._features(points, obj), counts, True)
        density = self._density(points, raw)
        albedo = torch.sigmoid(raw_albedo.float())  # type: ignore[union-attr]
        normal = None
        if with_normals:  # six probes per point, each under its point's object
            probe_obj = obj.repeat_interleave(6)
            probe_counts = [6 * c for c in counts]
            normal = central_difference_normals(lambda p: self.density(p, probe_obj, probe_counts), points,
                                                self.config.normal_eps)
        return FieldSample(density, albedo, normal)

    def _check(self, points: Tensor, obj: Tensor, counts: Sequence[int]) -> None:
        if len(counts) != len(self.fields) or sum(counts) != points.shape[0] or obj.shape != points.shape[:1]:
            raise ValueError(f"{len(self.fields)} fields: counts {list(counts)} must sum to the {points.shape[0]} "
                             f"points and obj must be ({points.shape[0]},), got {tuple(obj.shape)}")
