"""`phim train`: the training loop (one process, or one per GPU/CPU under torchrun with DDP).

A run directory holds:
    train.json     the TrainConfig of the run (a resumed run must match it, except `steps` and `init`)
    metrics.csv    one row per logged step (loss parts, learning rate, scans/s)
    state.pt       model, optimizer and step: what `--resume` continues from (the learning rate is a
                   function of the step, so `--resume --steps N` can also lengthen a run; a run stopped by
                   its time budget, `--max-minutes`, saves it and continues the same way)
    model.pt       the latest weights as a phim checkpoint (`phim eval --checkpoint`, `phim serve`)
    tb/            TensorBoard events, when tensorboard is installed
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from lidar.datasets import DataKind, parse_data_spec
from lidar.selection import ClassMap, parse_class_map
from lidar.sources import scan_source
from model.checkpoint import init_weights, save_checkpoint
from model.config import POINT_FIELDS, PHiMConfig, get_config
from model.detector import PHiM
from model.train.data import SampleConfig, SampleStream, TrainSample
from model.train.distributed import Dist
from model.train.loss import LossConfig, LossParts
from model.train.optim import make_optimizer
from model.train.step import TrainStep

log = logging.getLogger("phim.train")
METRICS = ("step", "loss", "heatmap", "reg", "iou_branch", "iou_loss", "mean_iou", "lr", "scans_per_s")


@dataclass(frozen=True)
class TrainConfig:
    config: str = "tiny"  # model config name
    data: str = "sim"  # a data spec: sim, kitti:DIR, nuscenes:DIR, native:DIR, custom:DIR
    class_map: str = ""  # custom:DIR: label class -> PHiM class (lidar.selection.parse_class_map)
    steps: int = 6000
    batch_size: int = 1  # scans per step and process
    lr: float = 3e-3  # one-cycle peak
    weight_decay: float = 0.05  # the paper's; none on biases, norms, A_log and D (model/train/optim.py)
    grad_clip: float = 10.0
    pct_start: float = 0.3  # share of the steps spent warming up to the peak
    div_factor: float = 10.0  # start lr = peak / div_factor
    final_div_factor: float = 100.0
    seed: int = 0  # the simulator's scan stream and the augmentation (evaluation uses seed 7)
    workers: int = 1  # data-loader processes per training process
    amp: bool = True  # bf16 autocast on CUDA (CPU runs in float32)
    init: str = ""  # a checkpoint whose weights start the run (its config must be the run's); "" = fresh init
    # point columns the model reads (x, y, z, intensity[, elongation]); 0: the config's own. 3 drops intensity
    # (docs/model.md); an `init` checkpoint reading more columns starts with their weights left out
    point_features: int = 0
    checkpoint_every: int = 200
    log_every: int = 10
    sample: SampleConfig = field(default_factory=SampleConfig)
    loss: LossConfig = field(default_factory=LossConfig)

    def __post_init__(self) -> None:
        if self.point_features and not 3 <= self.point_features <= len(POINT_FIELDS):
            raise ValueError(f"point_features: {self.point_features}; expected 0 or 3..{len(POINT_FIELDS)}")
        kind = parse_data_spec(self.data).kind
        if parse_class_map(self.class_map) != ClassMap() and kind is not DataKind.CUSTOM:
            raise ValueError(f"class_map {self.class_map!r}: applies to custom:DIR data only")
        if kind is DataKind.SAMPLES:
            raise ValueError(
                f"data {self.data!r}: the real samples' licences allow evaluation only; train on sim or on "
                "data you may train on (kitti:DIR, nuscenes:DIR, native:DIR, custom:DIR)"
            )

    def model_config(self) -> PHiMConfig:
        """The model config the run trains: `config`, reading `point_features` columns when set."""
        cfg = get_config(self.config)
        return cfg.reading(self.point_features) if self.point_features else cfg


def _plain(cfg: TrainConfig) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def _check_resume(out: Path, cfg: TrainConfig) -> None:
    saved = json.loads((out / "train.json").read_text())
    mine, defaults = _plain(cfg), _plain(TrainConfig())  # a field newer than the run: its default
    keys = sorted(set(saved) | set(mine))
    free = ("steps", "init")  # a resumed run may be lengthened, and has its own weights (not --init's)
    diff = [k for k in keys if k not in free and saved.get(k, defaults.get(k)) != mine.get(k)]
    if diff:
        raise ValueError(f"--resume: {out}/train.json differs from this run in {', '.join(diff)}")


def _cos(start: float, end: float, pct: float) -> float:
    return end + (start - end) / 2.0 * (math.cos(math.pi * pct) + 1)


def one_cycle(step: int, cfg: TrainConfig) -> tuple[float, float]:
    """(learning rate, Adam beta1) at 0-based `step`, as torch's OneCycleLR (cosine; beta1 0.95-0.85-0.95)."""
    peak, start_lr = cfg.lr, cfg.lr / cfg.div_factor
    warm_end = float(cfg.pct_start * cfg.steps) - 1
    if step <= warm_end:
        pct = step / warm_end if warm_end > 0 else 1.0
        return _cos(start_lr, peak, pct), _cos(0.95, 0.85, pct)
    pct = min(1.0, (step - warm_end) / max(cfg.steps - 1 - warm_end, 1e-9))
    return _cos(peak, start_lr / cfg.final_div_factor, pct), _cos(0.85, 0.95, pct)


def _set_schedule(opt: torch.optim.Optimizer, step: int, cfg: TrainConfig) -> float:
    lr, beta1 = one_cycle(step, cfg)
    for group in opt.param_groups:
        group["lr"] = lr
        group["betas"] = (beta1, group["betas"][1])
    return lr


BANK_STREAM = 1000  # the object bank of ground-truth sampling comes from data stream seed + BANK_STREAM


def _loader(cfg: TrainConfig, model: PHiM, dist: Dist, start_step: int) -> torch.utils.data.DataLoader:
    gts = cfg.sample.gt_sampling
    scans_per_step = dist.world * cfg.batch_size
    sample = cfg.sample
    if gts is not None:  # a short run cuts its bank from no more scans than it trains on
        bank_scans = min(gts.bank_scans, cfg.steps * scans_per_step)
        sample = dataclasses.replace(sample, gt_sampling=dataclasses.replace(gts, bank_scans=bank_scans))
    classes = parse_class_map(cfg.class_map)
    stream = SampleStream(
        scan_source(cfg.data, cfg.seed, classes=classes),
        model.cfg,
        sample,
        cfg.seed,
        first=dist.rank + start_step * scans_per_step,
        stride=dist.world,
        # sim: a stream training never reads
        bank_at=scan_source(cfg.data, cfg.seed + BANK_STREAM, classes=classes),
        paste_before=0 if gts is None else int(cfg.steps * gts.fade) * scans_per_step,
    )
    return torch.utils.data.DataLoader(
        stream,
        batch_size=cfg.batch_size,
        collate_fn=list,
        num_workers=cfg.workers,
        persistent_workers=cfg.workers > 0,
        prefetch_factor=2 if cfg.workers > 0 else None,
    )


class _Logger:
    """metrics.csv (appended across resumes), TensorBoard when installed, a progress line."""

    def __init__(self, out: Path, first: int):
        self.csv_path = out / "metrics.csv"
        new = not self.csv_path.exists()
        if not new:  # a resumed run: drop rows logged after the checkpoint it resumes from
            lines = self.csv_path.read_text().splitlines(keepends=True)
            self.csv_path.write_text(
                "".join(lines[:1] + [r for r in lines[1:] if int(r.split(",")[0]) <= first])
            )
        self.file = self.csv_path.open("a", newline="")
        self.writer = csv.writer(self.file)
        if new:
            self.writer.writerow(METRICS)
        self.tb = None
        try:
            from torch.utils.tensorboard import SummaryWriter

            self.tb = SummaryWriter(str(out / "tb"))
        except ImportError:
            log.info("tensorboard not installed: metrics go to %s only", self.csv_path)

    def write(self, row: dict[str, float]) -> None:
        self.writer.writerow([row[k] for k in METRICS])
        self.file.flush()
        if self.tb is not None:
            for k in METRICS[1:]:
                self.tb.add_scalar(f"train/{k}", row[k], int(row["step"]))

    def close(self) -> None:
        self.file.close()
        if self.tb is not None:
            self.tb.close()


def _save(out: Path, step: int, model: PHiM, opt: torch.optim.Optimizer, cfg: TrainConfig) -> None:
    state = {
        "step": step,
        "model": model.state_dict(),
        "optimizer": opt.state_dict(),
    }
    tmp = out / "state.pt.tmp"
    torch.save(state, tmp)
    tmp.replace(out / "state.pt")
    meta = {"trained_steps": step, "train": _plain(cfg), "source": str(out)}
    save_checkpoint(out / "model.pt", model, meta=meta)


def _row(step: int, parts: LossParts, lr: float, scans_per_s: float) -> dict[str, float]:
    return {
        "step": step,
        "loss": float(parts.total.detach()),
        "heatmap": parts.heatmap,
        "reg": parts.reg,
        "iou_branch": parts.iou_branch,
        "iou_loss": parts.iou_loss,
        "mean_iou": parts.mean_iou,
        "lr": lr,
        "scans_per_s": scans_per_s,
    }


def train(
    cfg: TrainConfig,
    out: Path,
    resume: bool = False,
    device: str = "auto",
    progress: bool = True,
    max_minutes: float = 0.0,
) -> Path:
    """Train (or continue) a run in `out`; returns the path of its latest model.pt. With `max_minutes` > 0
    the run saves its state and stops after the first step that ends past that budget (all ranks at the
    same step); `resume=True` continues it. The budget is how this call runs, not part of the run's
    config, so each resumed call may have its own."""
    dist = Dist.from_env(device)
    torch.manual_seed(cfg.seed + dist.rank)
    model = PHiM(cfg.model_config()).to(dist.device).train()
    if cfg.init and not resume:  # a resumed run has its own weights
        model.load_state_dict(init_weights(cfg.init, model.cfg))
        log.info("starting from the weights of %s", cfg.init)
    step_fn: nn.Module = dist.wrap(TrainStep(model, cfg.loss))
    opt = make_optimizer(model, cfg.lr, cfg.weight_decay)
    start = 0
    if resume:
        _check_resume(out, cfg)
        state = torch.load(out / "state.pt", map_location=dist.device, weights_only=True)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        start = int(state["step"])
        log.info("resuming %s at step %d of %d", out, start, cfg.steps)
    elif dist.is_main:
        if (out / "state.pt").exists():
            raise FileExistsError(f"{out} already holds a run; pass --resume to continue it, or pick --out")
        out.mkdir(parents=True, exist_ok=True)
        (out / "train.json").write_text(json.dumps(_plain(cfg), indent=2) + "\n")
    logger = _Logger(out, start) if dist.is_main else None
    try:
        clock = _Budget(max_minutes, dist)
        last = _loop(cfg, out, model, step_fn, opt, dist, start, logger, progress, clock)
        # rank 0 may still be writing the run: a rank that tears its gloo group down while a peer is still
        # connected can abort at exit ("terminate called without an active exception", seen under load)
        dist.barrier()
        if last < cfg.steps:
            log.info(
                "stopped at step %d of %d after %.1f minutes (the --max-minutes budget); state saved, "
                "continue with --resume",
                last,
                cfg.steps,
                clock.minutes(),
            )
    finally:
        if logger is not None:
            logger.close()
        dist.close()
    return out / "model.pt"


class _Budget:
    """Wall-clock budget of one train() call; under DDP all ranks stop at the step where one runs out."""

    def __init__(self, max_minutes: float, dist: Dist):
        self.t0, self.limit_s, self.dist = time.perf_counter(), max_minutes * 60.0, dist

    def minutes(self) -> float:
        return (time.perf_counter() - self.t0) / 60.0

    def spent(self) -> bool:
        return self.limit_s > 0 and self.dist.any(time.perf_counter() - self.t0 >= self.limit_s)


def _loop(
    cfg, out, model, step_fn, opt, dist: Dist, start: int, logger, progress: bool, clock: _Budget
) -> int:
    """Steps start + 1 .. cfg.steps, or fewer when the clock runs out; returns the last step done."""
    from model.train.progress import Progress

    bar = Progress(cfg.steps, start, enabled=progress and dist.is_main)
    batches = iter(_loader(cfg, model, dist, start))
    t_last, n_last = time.perf_counter(), start
    step = start
    for step in range(start + 1, cfg.steps + 1):
        batch: list[TrainSample] = next(batches)
        with dist.autocast(cfg.amp):
            parts = step_fn(batch)
        if not torch.isfinite(parts.total.detach()):
            raise FloatingPointError(f"step {step}: loss is {float(parts.total)} ({batch[0].name})")
        opt.zero_grad(set_to_none=True)
        parts.total.backward()
        nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        lr = _set_schedule(opt, step - 1, cfg)
        opt.step()
        if step % cfg.log_every == 0 or step == cfg.steps:
            now = time.perf_counter()
            rate = (step - n_last) * cfg.batch_size * dist.world / max(now - t_last, 1e-9)
            t_last, n_last = now, step
            if logger is not None:
                row = _row(step, parts, lr, rate)
                logger.write(row)
                bar.update(step, row)
        stop = clock.spent()
        if dist.is_main and (step % cfg.checkpoint_every == 0 or step == cfg.steps or stop):
            _save(out, step, model, opt, cfg)
        if stop:
            break
    bar.close()
    return step
