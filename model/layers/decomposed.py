"""Decomposed down- and up-sampling of a PHiM block (paper Sec. 3.3): sparse 2D convs on (r, z), (theta, z).

Down (kernel k, stride s), each conv followed by BatchNorm1d (eps 1e-3, momentum 0.01) and ReLU:
  (a) sparse conv on Plane.RZ, stride (s, s) on (r, z)
  (b) submanifold conv on Plane.RZ
  (c) sparse conv on Plane.THETA_Z, kernel (k, kz) and stride (s, 1) on (theta, z); kz = `tz_kernel_z`
Up: inverse conv of (c), then inverse conv of (a), each with BatchNorm1d + ReLU; the result lies exactly on
the down-sampling input's sites, in its row order.

Choices:
- The paper's "z stride min(s, remaining z extent)" needs no special case: the output extent
  floor((Z + 2p - k) / s) + 1 = ceil(Z / s) (odd k) is never below 1, and any s >= Z gives the same single
  output row and the same rule book as s = Z.
- s == 1: (a) and (c) are submanifold convs (no dilation of the active set, so the block keeps its sites and
  its cost); (a) and (b) then share one rule book, and the up-sampling convs are the transposed submanifold
  convs on the same rule books.
- BatchNorm over fewer than 2 sites in training mode uses the running statistics (and does not update them):
  batch statistics of one site are meaningless and an empty batch would write NaN into the running stats.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch.nn.functional as F
from torch import Tensor, nn

from model.geometry.rulebook import Plane, Rulebook
from model.geometry.sparse_tensor import SparseTensor
from model.layers.sparse_conv import SparseConv2d, SparseInverseConv2d

BN_EPS = 1e-3
BN_MOMENTUM = 0.01


def make_bn(channels: int) -> nn.BatchNorm1d:
    return nn.BatchNorm1d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


def bn_relu(bn: nn.BatchNorm1d | nn.Identity, x: SparseTensor) -> SparseTensor:
    """BatchNorm1d + ReLU over the features (N, C) of x; safe for N < 2 (see module docstring). `bn` is an
    Identity once folded into the conv before it (`model.fold_bn`)."""
    f: Tensor = x.features
    if isinstance(bn, nn.BatchNorm1d) and bn.training and f.shape[0] < 2:
        f = F.batch_norm(f, bn.running_mean, bn.running_var, bn.weight, bn.bias, False, 0.0, bn.eps)
    else:
        f = bn(f)
    return x.replace(F.relu(f, inplace=True))  # f is fresh: a BatchNorm's output, or a folded conv's


@dataclass(frozen=True)
class DownContext:
    """The rule books of down-sampling convs (a), (b), (c): DecomposedUp needs (a) and (c); a block with the
    same kernel and stride over the same sites reuses all three (they depend on the sites only)."""

    rz: Rulebook  # conv (a): input = the block's sites
    sub: Rulebook  # conv (b): input = the sites after (a); the same rule book as (a) when s == 1
    theta_z: Rulebook  # conv (c): input = the sites after (a) / (b)


def _check(kernel: int, stride: int) -> None:
    if kernel < 1 or kernel % 2 == 0:
        raise ValueError(f"decomposed convs need an odd kernel, got {kernel}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")


class DecomposedDown(nn.Module):
    """(N, C) sparse voxels -> (M, C) coarser sites; channels constant."""

    def __init__(self, channels: int, kernel: int, stride: int, tz_kernel_z: int) -> None:
        super().__init__()
        _check(kernel, stride)
        _check(tz_kernel_z, 1)
        self.stride = stride
        subm = stride == 1
        tz_kernel = (kernel, tz_kernel_z)
        self.conv_rz = SparseConv2d(channels, channels, kernel, (stride, stride), Plane.RZ, subm=subm)
        self.conv_sub = SparseConv2d(channels, channels, kernel, (1, 1), Plane.RZ, subm=True)
        self.conv_tz = SparseConv2d(channels, channels, tz_kernel, (stride, 1), Plane.THETA_Z, subm=subm)
        self.bn_rz, self.bn_sub, self.bn_tz = make_bn(channels), make_bn(channels), make_bn(channels)

    def forward(self, x: SparseTensor, ctx: DownContext | None = None) -> tuple[SparseTensor, DownContext]:
        """x (N, C) -> (M, C) and the rule books; a given `ctx` (built for x's sites, this kernel and stride)
        is reused instead of building them again."""
        h, rb_rz = self.conv_rz(x, None if ctx is None else ctx.rz)
        h = bn_relu(self.bn_rz, h)
        rb_sub = ctx.sub if ctx is not None else rb_rz if self.stride == 1 else None  # s == 1: same sites
        h, rb_sub = self.conv_sub(h, rb_sub)
        h = bn_relu(self.bn_sub, h)
        h, rb_tz = self.conv_tz(h, None if ctx is None else ctx.theta_z)
        h = bn_relu(self.bn_tz, h)
        return h, DownContext(rz=rb_rz, sub=rb_sub, theta_z=rb_tz)


class DecomposedUp(nn.Module):
    """(M, C) coarse sites -> (N, C) exactly at the paired DecomposedDown input's sites, in its row order."""

    def __init__(self, channels: int, kernel: int, stride: int, tz_kernel_z: int) -> None:
        super().__init__()
        _check(kernel, stride)
        _check(tz_kernel_z, 1)
        self.stride = stride  # the paired DecomposedDown's; the rule books carry the geometry
        self.inv_tz = SparseInverseConv2d(channels, channels, (kernel, tz_kernel_z), Plane.THETA_Z)
        self.inv_rz = SparseInverseConv2d(channels, channels, kernel, Plane.RZ)
        self.bn_tz, self.bn_rz = make_bn(channels), make_bn(channels)

    def forward(self, y: SparseTensor, ctx: DownContext) -> SparseTensor:
        h = bn_relu(self.bn_tz, self.inv_tz(y, ctx.theta_z))
        return bn_relu(self.bn_rz, self.inv_rz(h, ctx.rz))
