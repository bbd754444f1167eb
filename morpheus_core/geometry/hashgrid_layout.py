"""A hash grid's layout: its configuration (``HashGridConfig``) and the per-level constants every
encoder needs (``LevelTables``): the eager encoder (``hashgrid``) and the Triton kernels
(``hashgrid_triton``) both read them here, so the kernels never import the module that chooses them."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch

PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class HashGridConfig:
    """A multi-resolution hash grid (defaults: the paper's), with threestudio's progressive level masking."""

    n_levels: int = 16
    """Resolution levels of the grid (the paper: 16)."""
    n_features_per_level: int = 2
    """Features stored per level (the paper: 2); the encoding is n_levels × this wide."""
    log2_table_size: int = 19
    """log2 of each level's hash-table rows (the paper: 2^19); coarse levels that fit are stored densely."""
    base_resolution: int = 16
    """Grid resolution (cells per side) of the coarsest level (the paper: 16)."""
    per_level_scale: float = 1.447269237440378
    """Resolution growth per level (≥ 1); 2^(8/15) takes 16 levels from 16 to ≈ 4096, the paper's finest."""
    start_levels: int | None = None
    """Levels active at first under progressive masking (threestudio); None or n_levels: all, no masking."""
    start_step: int = 0
    """Step from which progressive masking switches on one more level every ``update_steps``."""
    update_steps: int = 500
    """Steps between switching on successive levels under progressive masking."""

    def __post_init__(self) -> None:
        if self.n_levels < 1 or self.n_features_per_level < 1:
            raise ValueError("a hash grid needs at least one level and one feature per level")
        if not 1 <= self.log2_table_size <= 30:
            raise ValueError(f"log2_table_size must be in [1, 30], got {self.log2_table_size}")
        if self.base_resolution < 1 or self.per_level_scale < 1.0:
            raise ValueError("base_resolution must be ≥ 1 and per_level_scale ≥ 1")
        if self.start_levels is not None and not 1 <= self.start_levels <= self.n_levels:
            raise ValueError(f"start_levels must be in [1, {self.n_levels}], got {self.start_levels}")
        if self.update_steps < 1:
            raise ValueError("update_steps must be ≥ 1")

    @property
    def output_dim(self) -> int:
        return self.n_levels * self.n_features_per_level

    def levels_at(self, step: int) -> int:
        """How many levels the progressive schedule has switched on at ``step``."""
        if self.start_levels is None:
            return self.n_levels
        grown = max(step - self.start_step, 0) // self.update_steps
        return min(self.n_levels, self.start_levels + grown)

    def level_layout(self) -> list[tuple[float, int, int, bool]]:
        """Per level: (scale, resolution, table rows, is_hashed)."""
        table = 2**self.log2_table_size
        layout = []
        for level in range(self.n_levels):
            scale = math.exp2(level * math.log2(self.per_level_scale)) * self.base_resolution - 1.0
            res = math.ceil(scale) + 1
            dense_rows = -(-(res**3) // 8) * 8
            rows = min(dense_rows, table)
            layout.append((scale, res, rows, dense_rows > table))
        return layout


class LevelTables:
    """The constant per-level tensors the encoders (eager and Triton) need, built once per device."""

    def __init__(self, config: HashGridConfig, device: torch.device) -> None:
        layout = config.level_layout()
        hashed = [h for _, _, _, h in layout]
        # Resolution grows with the level, so the dense levels are a prefix of the list.
        self.n_dense = hashed.index(True) if any(hashed) else len(hashed)
        self.scale = torch.tensor([s for s, _, _, _ in layout], dtype=torch.float64, device=device)
        res = torch.tensor([r for _, r, _, _ in layout], dtype=torch.int64, device=device)
        self.rows = torch.tensor([n for _, _, n, _ in layout], dtype=torch.int64, device=device)
        self.offsets = torch.cumsum(self.rows, 0) - self.rows
        self.strides = torch.stack((torch.ones_like(res), res, res * res), -1)  # (L, 3)
        self.primes = torch.tensor(PRIMES, dtype=torch.int64, device=device)
        self.steps = torch.tensor([0, 1], dtype=torch.int64, device=device)

    @property
    def n_levels(self) -> int:
        return int(self.scale.shape[0])

    def first(self, n: int) -> LevelTables:
        """The tables of levels 0..n−1 only: their rows keep their offsets in the whole table, so an encode
        on them reads and writes the same rows as the whole grid's levels 0..n−1 do."""
        if not 1 <= n <= self.n_levels:
            raise ValueError(f"a level prefix must hold 1 to {self.n_levels} levels, got {n}")
        part = copy.copy(self)
        part.n_dense = min(self.n_dense, n)
        part.scale, part.rows, part.offsets, part.strides = (t[:n] for t in (self.scale, self.rows, self.offsets,
                                                                             self.strides))
        return part
