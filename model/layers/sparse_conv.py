"""Sparse (and submanifold) 2D conv layers on one plane of the polar grid, and their inverse: each builds or
reuses a rule book (`model.geometry.rulebook`) and runs `model.ops.sparse_conv.gather_mm_scatter`."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from model.geometry.rulebook import Plane, Rulebook, as_kernel, build_strided_rulebook, build_subm_rulebook
from model.geometry.sparse_tensor import SparseTensor
from model.ops.sparse_conv import gather_mm_scatter


def _init_params(weight: Tensor, bias: Tensor | None, fan_in: int) -> None:
    """PyTorch's conv default (kaiming-uniform with a = sqrt(5)): U(-1/sqrt(fan_in), 1/sqrt(fan_in))."""
    bound = 1.0 / math.sqrt(fan_in)
    with torch.no_grad():
        weight.uniform_(-bound, bound)
        if bias is not None:
            bias.uniform_(-bound, bound)


class SparseConv2d(nn.Module):
    """Sparse (or submanifold) 2D conv on `plane`; weight (K0*K1, in_ch, out_ch)."""

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int | tuple[int, int],
        stride: tuple[int, int],
        plane: Plane,
        subm: bool = False,
        bias: bool = False,
    ) -> None:
        super().__init__()
        k = as_kernel(kernel)
        if subm and (tuple(stride) != (1, 1) or k[0] % 2 == 0 or k[1] % 2 == 0):
            raise ValueError(f"a submanifold conv needs stride (1, 1) and an odd kernel: {stride}, {kernel}")
        self.kernel, self.plane, self.subm = k, plane, subm
        self.stride = (int(stride[0]), int(stride[1]))
        self.weight = nn.Parameter(torch.empty(k[0] * k[1], in_ch, out_ch))
        self.bias = nn.Parameter(torch.empty(out_ch)) if bias else None
        _init_params(self.weight, self.bias, k[0] * k[1] * in_ch)

    def rulebook(self, x: SparseTensor) -> Rulebook:
        if self.subm:
            return build_subm_rulebook(x.coords, x.spatial_shape, x.batch_size, self.kernel, self.plane)
        return build_strided_rulebook(
            x.coords, x.spatial_shape, x.batch_size, self.kernel, self.stride, self.plane
        )

    def forward(self, x: SparseTensor, rulebook: Rulebook | None = None) -> tuple[SparseTensor, Rulebook]:
        """x (N, in_ch) -> (M, out_ch) and the rule book; a given `rulebook` (built for x) is reused."""
        rb = self.rulebook(x) if rulebook is None else rulebook
        if rb.num_in != x.num_sites or rb.kernel != self.kernel or rb.plane != self.plane:
            raise ValueError("rule book does not match this conv / input")
        feats = gather_mm_scatter(
            x.features, self.weight, rb.in_idx, rb.out_idx, rb.offset_ptr, rb.num_out, rb.identity_offset
        )
        if self.bias is not None:
            feats = feats + self.bias
        return SparseTensor(feats, rb.out_coords, rb.out_shape, rb.batch_size), rb


class SparseInverseConv2d(nn.Module):
    """Transposed conv onto a paired conv's input sites via its rule book reversed.

    weight (K0*K1, in_ch, out_ch), with the paired conv's kernel.
    """

    def __init__(
        self, in_ch: int, out_ch: int, kernel: int | tuple[int, int], plane: Plane, bias: bool = False
    ) -> None:
        super().__init__()
        k = as_kernel(kernel)
        self.kernel, self.plane = k, plane
        self.weight = nn.Parameter(torch.empty(k[0] * k[1], in_ch, out_ch))
        self.bias = nn.Parameter(torch.empty(out_ch)) if bias else None
        _init_params(self.weight, self.bias, k[0] * k[1] * in_ch)

    def forward(self, y: SparseTensor, rulebook: Rulebook) -> SparseTensor:
        """y (M, in_ch) at the rule book's output sites -> (N, out_ch) at its input sites (same row order)."""
        rb = rulebook
        if rb.num_out != y.num_sites or rb.kernel != self.kernel or rb.plane != self.plane:
            raise ValueError("rule book does not match this inverse conv / input")
        feats = gather_mm_scatter(
            y.features, self.weight, rb.out_idx, rb.in_idx, rb.offset_ptr, rb.num_in, rb.identity_offset
        )
        if self.bias is not None:
            feats = feats + self.bias
        return SparseTensor(feats, rb.in_coords, rb.in_shape, rb.batch_size)
