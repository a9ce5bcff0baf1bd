"""Process-group handling: a plain single process, or DDP under torchrun (NCCL on GPUs, gloo on CPUs)."""

from __future__ import annotations

import contextlib
import logging
import os
import warnings
from dataclasses import dataclass

import torch
import torch.distributed as torch_dist
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from model.device import pick_device

log = logging.getLogger("phim.train")


@dataclass(frozen=True)
class Dist:
    rank: int
    world: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @staticmethod
    def from_env(device: str = "auto") -> Dist:
        """torchrun sets WORLD_SIZE, RANK and LOCAL_RANK; without them this is one process."""
        world = int(os.environ.get("WORLD_SIZE", "1"))
        dev = pick_device(device)
        if world == 1:
            log.info("training on %s, one process", dev)
            return Dist(0, 1, dev)
        rank, local = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
        if dev.type == "cuda":
            if local >= torch.cuda.device_count():
                raise RuntimeError(
                    f"LOCAL_RANK {local} but only {torch.cuda.device_count()} CUDA device(s): "
                    "start at most one process per GPU (torchrun --nproc_per_node), or pass --device cpu"
                )
            dev = torch.device("cuda", local)
            torch.cuda.set_device(dev)
        backend = "nccl" if dev.type == "cuda" else "gloo"
        torch_dist.init_process_group(backend=backend)
        log.info("DDP rank %d of %d on %s (%s)", rank, world, dev, backend)
        return Dist(rank, world, dev)

    def wrap(self, module: nn.Module) -> nn.Module:
        if self.world == 1:
            return module
        ids = [self.device.index] if self.device.type == "cuda" else None
        # the BEV shortcuts' 1 x 1 conv weight grads come back with other strides on their size-1 dims: the
        # same memory, contiguous, but DDP's reducer compares strides and warns on every rank
        warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")
        return DistributedDataParallel(module, device_ids=ids)

    def any(self, flag: bool) -> bool:
        """True on every rank when `flag` is true on at least one (a collective call under DDP)."""
        if self.world == 1:
            return flag
        t = torch.tensor([float(flag)], device=self.device)
        torch_dist.all_reduce(t, op=torch_dist.ReduceOp.MAX)
        return bool(t.item())

    def autocast(self, enabled: bool) -> contextlib.AbstractContextManager:
        """bf16 autocast on CUDA when enabled; float32 otherwise (CPU autocast would only slow us down)."""
        if enabled and self.device.type == "cuda":
            return torch.autocast("cuda", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def barrier(self) -> None:
        """Wait until every rank is here (under DDP)."""
        if self.world > 1:
            torch_dist.barrier()

    def close(self) -> None:
        if self.world > 1 and torch_dist.is_initialized():
            torch_dist.destroy_process_group()
