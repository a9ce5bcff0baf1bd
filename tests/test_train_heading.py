"""Teaching a trained detector a new heading code: `phim train --heading axis_vector --trainable head.rot`
(model/train/loop.py `freeze_all_but`, model/checkpoint.py `init_weights`)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from model.checkpoint import load_checkpoint, save_checkpoint
from model.config import HeadingCode, tiny
from model.detector import PHiM
from model.train.data import SampleConfig
from model.train.loop import TrainConfig, train


def test_only_the_trainable_parameters_move_and_frozen_batch_norms_keep_their_statistics(tmp_path: Path):
    torch.manual_seed(5)
    start = PHiM(tiny())
    save_checkpoint(tmp_path / "start.pt", start)
    cfg = TrainConfig(
        steps=2,
        lr=1e-2,
        workers=0,
        log_every=1,
        init=str(tmp_path / "start.pt"),
        heading="axis_vector",
        trainable=("head.rot",),
        sample=SampleConfig(gt_sampling=None),  # no object bank to cut: what is shown does not need one
    )
    trained = load_checkpoint(train(cfg, tmp_path / "run", device="cpu", progress=False))
    assert trained.cfg.head.heading is HeadingCode.AXIS_VECTOR
    before, after = start.state_dict(), trained.state_dict()
    assert before.keys() == after.keys()
    for key, value in before.items():  # weights, biases and running statistics alike
        if not key.startswith("head.rot."):
            assert torch.equal(after[key], value), key
    rot = after["head.rot.0.weight"]  # (4, C, 3, 3): the axis channels and the new (sin, cos) ones
    assert not torch.equal(rot[:2], before["head.rot.0.weight"][:2])  # the axis channels train too
    assert rot[2:].abs().sum() > 0  # the end channels started at zero and learnt
    with pytest.raises(ValueError, match=r"trainable head\.nothing: no parameter"):
        train(
            TrainConfig(steps=1, workers=0, trainable=("head.nothing",)),
            tmp_path / "bad",
            device="cpu",
            progress=False,
        )
