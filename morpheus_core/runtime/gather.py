"""Row gathers whose gradient is cheap on CUDA.

``table[index]`` (advanced indexing) and ``gather_rows(table, index)`` give the same values. Their
backward passes differ on CUDA: advanced indexing scatters its gradient with a sort-based
``index_put_(accumulate=True)`` (a radix sort of every index plus ``indexing_backward_kernel``,
~1 ms per call at the DMTet stage's pixel counts and 24 % of that stage's GPU time on an H200,
``benchmarks/results/paper_profile_after_h200_b8profile.txt``), while ``index_select``'s backward is
one ``index_add_`` with atomics. The price is the atomics' summation order, which is not fixed on
CUDA (the hash-grid backward already accepts that); on the CPU both are sequential.
"""

from __future__ import annotations

from torch import Tensor


def gather_rows(table: Tensor, index: Tensor) -> Tensor:
    """``table[index]`` for an integer ``index`` of any shape: (*index.shape, *table.shape[1:])."""
    return table.index_select(0, index.reshape(-1)).reshape(*index.shape, *table.shape[1:])


def gather_batched_rows(table: Tensor, batch_index: Tensor, index: Tensor) -> Tensor:
    """``table[batch_index, index]`` for a (B, V, ...) ``table`` and broadcastable integer indices."""
    flat = table.reshape(table.shape[0] * table.shape[1], *table.shape[2:])
    return gather_rows(flat, batch_index * table.shape[1] + index)
