"""How the graph engine compiles its step: torch.compile's options, the guards it keeps, and the recompile
limit a thread needs to compile one graph per (batch, capacity) bucket."""

from __future__ import annotations

from collections.abc import Callable

import torch

from model.graph.step import GraphStep


def compile_step(step: GraphStep, device: torch.device) -> Callable:
    """`step` through torch.compile(fullgraph=True, dynamic=False): one specialisation per bucket. On CUDA
    each bucket's graph is captured as a CUDA graph and replayed (mode "reduce-overhead"): its outputs are
    overwritten by the next replay, and by then the engine has copied them out (the host tensor to the host,
    the new states into their slots); on the CPU the code that calls the graph's kernels is C++, not Python
    ("cpp_wrapper": 3-4 % off a tiny step, docs/benchmarks.md)."""
    cuda = device.type == "cuda"
    options = {"triton.cudagraphs": cuda, "cpp_wrapper": not cuda, "guard_filter_fn": live_module_tree}
    return torch.compile(step, fullgraph=True, dynamic=False, options=options)


def allow_bucket_graphs() -> None:
    """torch.compile's recompile limit (default 8) is a per-thread setting and the step compiles one graph per
    (batch, capacity) bucket in whichever thread runs it (a server's device thread): raise it there."""
    cfg = torch._dynamo.config
    cfg.recompile_limit = max(cfg.recompile_limit, 64)


def live_module_tree(entries: list) -> list[bool]:
    """torch.compile's guard filter (True: keep) for the step module: no guards on its module tree and its
    parameters and buffers, which are a detector's own for its lifetime and read live as graph inputs (with
    them the guards took 0.5 ms a step on the CPU); the constants read while tracing (config fields, channel
    counts) stay guarded (~0.3 ms, ~0.2 without them), so that a second detector whose config differs in one
    compiles its own graph rather than reusing the first's (dynamo caches per code object)."""
    return [not _module_tree_guard(e) for e in entries]


def _module_tree_guard(entry) -> bool:
    if not entry.orig_guard.source.is_unspecialized_nn_module():
        return False
    constant = entry.guard_type in ("CONSTANT_MATCH", "EQUALS_MATCH", "SEQUENCE_LENGTH", "ID_MATCH")
    return not constant or any(part in entry.name for part in ("_parameters", "_buffers", "hooks"))
