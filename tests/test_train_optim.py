"""The optimizer's weight decay (model/train/optim.py): matrices and kernels decay; biases, norm scales and
Mamba's A_log and D never do; every parameter is in exactly one group; the training loop uses it."""

from __future__ import annotations

from torch import nn

from model.config import tiny
from model.detector import PHiM
from model.train.optim import make_optimizer, param_groups


def named_groups(model: nn.Module, weight_decay: float) -> tuple[set[str], set[str]]:
    names = {id(p): n for n, p in model.named_parameters()}
    decay, keep = param_groups(model, weight_decay)
    assert decay["weight_decay"] == weight_decay and keep["weight_decay"] == 0.0
    return {names[id(p)] for p in decay["params"]}, {names[id(p)] for p in keep["params"]}


def test_only_matrices_and_kernels_decay() -> None:
    model = PHiM(tiny())
    decay, keep = named_groups(model, 0.05)
    every = {n for n, _ in model.named_parameters()}
    assert decay | keep == every and not decay & keep  # each parameter once
    mamba = {n for n in every if n.endswith((".A_log", ".D"))}
    biases = {n for n in every if n.endswith(".bias")}
    norms = {
        f"{m}.{p}"
        for m, mod in model.named_modules()
        if isinstance(mod, nn.LayerNorm | nn.BatchNorm1d | nn.BatchNorm2d)
        for p, _ in mod.named_parameters(recurse=False)
    }
    assert mamba and biases and norms
    assert mamba | biases | norms <= keep, sorted((mamba | biases | norms) - keep)[:5]
    linears = {f"{m}.weight" for m, mod in model.named_modules() if isinstance(mod, nn.Linear | nn.Conv2d)}
    assert linears and linears <= decay


def test_the_optimizer_applies_the_groups() -> None:
    model = PHiM(tiny())
    opt = make_optimizer(model, lr=1e-3, weight_decay=0.05)
    a_log = next(p for n, p in model.named_parameters() if n.endswith(".A_log"))
    group = next(g for g in opt.param_groups if any(p is a_log for p in g["params"]))
    assert group["weight_decay"] == 0.0 and group["lr"] == 1e-3
