"""The two mat-vecs with a model basis stored transposed, Uᵀ (K, 3N) contiguous, on every thread.

On the CPU, torch's mat-vec (MKL's sgemv) streams a large basis from one thread however many it
has: 2^20 vertices, K = 100, two threads, ≈ 58 ms per product, 22 GB/s of a machine that reads
31 GB/s. Written as a batch of products over as many column blocks as there are intra-op threads,
each thread streams its own block: ≈ 42 ms (docs/benchmarks.md §1). One thread, or a GPU, keeps
the plain mat-vec, which is as fast or faster there (a head-sized basis on one thread: 0.47 ms
plain vs 0.68 ms blocked).
"""
from __future__ import annotations

import torch


def _blocks(basis_t: torch.Tensor) -> tuple[int, int, int]:
    """(blocks, width, head) for a product with ``basis_t`` (K, 3N): as many column blocks of
    ``width`` columns as intra-op threads on the CPU (1 elsewhere, or for fewer columns than
    threads: the plain mat-vec); they cover the first ``head`` columns, a plain mat-vec the rest."""
    blocks = torch.get_num_threads() if basis_t.device.type == "cpu" else 1
    width = basis_t.shape[1] // blocks
    if width == 0:
        blocks, width = 1, basis_t.shape[1]
    return blocks, width, blocks * width


def project(basis_t: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Uᵀ v: (K,) for ``basis_t`` (K, 3N) and ``v`` (3N,)."""
    blocks, width, head = _blocks(basis_t)
    k, columns = basis_t.shape
    if blocks == 1:
        return torch.mv(basis_t, v)
    block_rows = basis_t[:, :head].view(k, blocks, width).permute(1, 2, 0)          # (B, width, K)
    out = torch.bmm(v[:head].reshape(blocks, 1, width), block_rows).sum(0).view(k)
    if head < columns:
        out += torch.mv(basis_t[:, head:], v[head:])
    return out


def expand(basis_t: torch.Tensor, coeff: torch.Tensor, base: torch.Tensor | None = None,
           base_weight: float = 1.0, basis: torch.Tensor | None = None) -> torch.Tensor:
    """U coeff, plus ``base_weight`` · base if given: (3N,) for ``basis_t`` (K, 3N), ``coeff`` (K,),
    ``base`` (3N,); ``basis``: ``basis_t.t()`` if the caller keeps that view (one op less per call)."""
    blocks, width, head = _blocks(basis_t)
    k, columns = basis_t.shape
    if blocks == 1:
        basis = basis_t.t() if basis is None else basis
        if base is None:
            return torch.mv(basis, coeff)
        return torch.addmv(base, basis, coeff, beta=base_weight)
    out = torch.empty(columns, dtype=basis_t.dtype, device=basis_t.device)
    block_rows = basis_t[:, :head].view(k, blocks, width).transpose(0, 1)           # (B, K, width)
    block_coeff = coeff.view(1, 1, k).expand(blocks, 1, k)
    block_out = out[:head].view(blocks, 1, width)
    if base is None:
        torch.bmm(block_coeff, block_rows, out=block_out)
    else:
        torch.baddbmm(base[:head].reshape(blocks, 1, width), block_coeff, block_rows, beta=base_weight, out=block_out)
    if head < columns:
        tail = basis_t[:, head:].t()
        if base is None:
            torch.mv(tail, coeff, out=out[head:])
        else:
            torch.addmv(base[head:], tail, coeff, beta=base_weight, out=out[head:])
    return out
