"""Per-object state shared by the priors: a batch row belongs to one object (one photo)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor


def check_rows(object_ids: Sequence[str], batch: int) -> tuple[str, ...]:
    ids = tuple(object_ids)
    if len(ids) != batch:
        raise ValueError(f"{len(ids)} object ids for a batch of {batch} rows")
    return ids


def gather_rows(cache: Mapping[str, Tensor], object_ids: Sequence[str], what: str) -> Tensor:
    """Stack each row's cached 1×… tensor, so one batch can mix objects freely."""
    missing = [o for o in dict.fromkeys(object_ids) if o not in cache]
    if missing:
        raise KeyError(f"no {what} for objects {missing}; call set_reference(object_id, image) first")
    return torch.cat([cache[o] for o in object_ids])
