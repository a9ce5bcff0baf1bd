"""An inference copy of a PHiM with every BatchNorm folded into the conv before it.

In eval mode a BatchNorm after a conv is an affine map per output channel, so it can move into the conv:

    s = gamma / sqrt(running_var + eps)            # (C_out,)
    W' = W * s (per output channel);  b' = (b - running_mean) * s + beta     (b = 0 for a conv without bias)

That saves the BatchNorm's pass over the activations where the conv adds its bias itself (the dense convs
on the CPU; a sparse conv, and a conv on a GPU, add the bias in a pass of their own, a cheaper one than the
BatchNorm's): the sparse convs of the decomposed down/up-sampling (30 in the paper config), the BEV
backbone's convs and transposed convs, the head's. The BatchNorm is replaced by `nn.Identity`; the unfolded
model is the plain twin (a test holds the two equal). The VFE folds its own BatchNorm in eval mode
already (`voxelize._VFELayer`). The copy is for inference only: training it would not train BatchNorms.
"""

from __future__ import annotations

import copy
import itertools

import torch
from torch import Tensor, nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from model.detector import PHiM
from model.layers.bev_backbone import BasicBlock
from model.layers.decomposed import DecomposedDown, DecomposedUp
from model.layers.sparse_conv import SparseConv2d, SparseInverseConv2d

# (conv, its BatchNorm) attribute pairs of the modules that are not an nn.Sequential
PAIRS: dict[type[nn.Module], tuple[tuple[str, str], ...]] = {
    BasicBlock: (("conv1", "bn1"), ("conv2", "bn2")),
    DecomposedDown: (("conv_rz", "bn_rz"), ("conv_sub", "bn_sub"), ("conv_tz", "bn_tz")),
    DecomposedUp: (("inv_tz", "bn_tz"), ("inv_rz", "bn_rz")),
}
_DENSE = (nn.Conv2d, nn.ConvTranspose2d)
_SPARSE = (SparseConv2d, SparseInverseConv2d)


def _bn_affine(bn: nn.modules.batchnorm._BatchNorm) -> tuple[Tensor, Tensor]:
    """Eval BatchNorm as y = x * scale + shift -> (scale (C,), shift (C,))."""
    assert bn.running_mean is not None and bn.running_var is not None
    scale = bn.weight * torch.rsqrt(bn.running_var + bn.eps)
    return scale, bn.bias - bn.running_mean * scale


def _fold_sparse(conv: SparseConv2d | SparseInverseConv2d, bn: nn.BatchNorm1d) -> None:
    """In place: conv (weight (KK, C_in, C_out), optional bias) absorbs bn."""
    scale, shift = _bn_affine(bn)
    bias = shift if conv.bias is None else conv.bias * scale + shift
    conv.weight = nn.Parameter(conv.weight * scale)  # scales the last axis, C_out
    conv.bias = nn.Parameter(bias)


def _fold(conv: nn.Module, bn: nn.Module) -> nn.Module | None:
    """The conv with bn folded in, or None when the pair is not a (conv, BatchNorm) pair."""
    if isinstance(conv, _SPARSE) and isinstance(bn, nn.BatchNorm1d):
        _fold_sparse(conv, bn)
        return conv
    if isinstance(conv, _DENSE) and isinstance(bn, nn.BatchNorm2d):
        return fuse_conv_bn_eval(conv, bn, transpose=isinstance(conv, nn.ConvTranspose2d))
    return None


def fold_batchnorms(model: PHiM) -> PHiM:
    """A copy of `model` in eval mode with every (conv, BatchNorm) pair folded; `model` is left as it is."""
    folded = copy.deepcopy(model).eval()
    with torch.no_grad():
        for module in list(folded.modules()):
            if isinstance(module, nn.Sequential):
                pairs = list(itertools.pairwise(module._modules))
            else:
                pairs = list(PAIRS.get(type(module), ()))
            for conv_name, bn_name in pairs:
                conv = _fold(getattr(module, conv_name), getattr(module, bn_name))
                if conv is not None:
                    setattr(module, conv_name, conv)
                    setattr(module, bn_name, nn.Identity())
    return folded.eval()  # the new modules too
