"""The multi-turn evaluation (`phim eval --turns`): turns streamed through the serving path score as the
single-turn evaluation, and, under MambaHistory.TURN, turn N as turn 1."""

from __future__ import annotations

import dataclasses

import numpy as np
from test_streaming import make_model

from lidar.sources import SimSource
from model.config import MambaHistory
from model.eval.runner import predict_scan
from model.eval.turns import run_turns, score_turns


def test_streamed_turns_equal_the_single_turn_eval_under_the_turn_history() -> None:
    model = make_model()
    scan = SimSource(7)(0)
    single = predict_scan(model, scan).predictions[-1]
    by_turn = run_turns(model, range(1), lambda i: scan, turns=3)
    assert len(single) > 0 and [len(rs) for rs in by_turn] == [1, 1, 1]
    for rs in by_turn:
        p = rs[0].predictions[-1]
        assert len(p) == len(single)
        np.testing.assert_allclose(np.sort(p.scores), np.sort(single.scores), atol=1e-5)
    scores = score_turns(by_turn)
    assert set(scores) == {"1", "2", "3"} and scores["1"] == scores["3"]


def test_the_stream_history_moves_later_turns() -> None:
    model = make_model()
    model.cfg = dataclasses.replace(model.cfg, history=MambaHistory.STREAM)
    scan = SimSource(7)(0)
    first, _, third = (rs[0].predictions[-1] for rs in run_turns(model, range(1), lambda i: scan, turns=3))
    same = len(first) == len(third) and np.array_equal(np.sort(first.scores), np.sort(third.scores))
    assert not same
