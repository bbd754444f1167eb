"""What every renderer returns, so stages and losses treat NeRF and mesh renders alike."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass
class RenderOutput:
    """Channels-last images, batch first: rgb (B,H,W,3) composited on the background,
    opacity (B,H,W,1) in [0, 1], depth (B,H,W,1) camera distance (0 where empty),
    normal (B,H,W,3) world-space unit normals (0 where empty)."""

    rgb: Tensor
    opacity: Tensor
    depth: Tensor
    normal: Tensor

    def split(self, sizes: Sequence[int]) -> list[RenderOutput]:
        """Consecutive batches of ``sizes`` views (they must add up to the batch)."""
        if sum(sizes) != self.rgb.shape[0]:
            raise ValueError(f"sizes {list(sizes)} do not add up to the {self.rgb.shape[0]} rendered views")
        parts = [t.split(list(sizes)) for t in (self.rgb, self.opacity, self.depth, self.normal)]
        return [RenderOutput(*views) for views in zip(*parts, strict=True)]

    @classmethod
    def cat(cls, parts: Sequence[RenderOutput]) -> RenderOutput:
        """One batch of every view of ``parts``, in order (the inverse of ``split``)."""
        if not parts:
            raise ValueError("RenderOutput.cat needs at least one render")
        return cls(*(torch.cat([getattr(p, name) for p in parts]) for name in ("rgb", "opacity", "depth", "normal")))

    def rgb_chw(self) -> Tensor:
        """(B,3,H,W): the layout the guidance and the priors take."""
        return self.rgb.permute(0, 3, 1, 2)

    def opacity_chw(self) -> Tensor:
        return self.opacity.permute(0, 3, 1, 2)
