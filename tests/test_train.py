"""Real (short) training runs on the simulator: checkpoints, resume, DDP under torchrun, then `phim eval`."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from lidar.sources import SimSource, sim_seed
from lidar.types import Predictions
from model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from model.config import CLASS_NAMES, tiny
from model.detector import PHiM
from model.eval.prediction_files import read_predictions, write_predictions
from model.eval.runner import ScanResult, predict_scan, score
from model.train.data import SampleConfig
from model.train.gt_sampling import GTSamplingConfig
from model.train.loop import TrainConfig, one_cycle, train

REPO = Path(__file__).resolve().parents[1]
SHORT = TrainConfig(steps=2, checkpoint_every=2, log_every=1, workers=0)


def _rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open() as f:
        return list(csv.DictReader(f))


def _saved_step(run: Path) -> int:
    return torch.load(run / "state.pt", weights_only=True)["step"]


def test_a_short_run_stops_on_its_time_budget_writes_checkpoints_and_resumes(tmp_path: Path):
    """One run, four steps in all: out of time after step 1, resumed to its end, then (as if it had died
    after logging step 2 with state.pt at step 1) resumed and lengthened to step 3."""
    run = tmp_path / "run"
    model_path = train(SHORT, run, device="cpu", progress=False, max_minutes=1e-9)  # out of time after step 1
    assert [r["step"] for r in _rows(run)] == ["1"]
    assert _saved_step(run) == 1  # saved though checkpoint_every is 2
    with pytest.raises(FileExistsError, match="--resume"):
        train(SHORT, run, device="cpu", progress=False)
    with pytest.raises(ValueError, match="lr"):
        train(TrainConfig(steps=4, lr=1.0, workers=0), run, resume=True, device="cpu", progress=False)
    train(SHORT, run, resume=True, device="cpu", progress=False, max_minutes=60)  # a budget it does not reach
    assert [r["step"] for r in _rows(run)] == ["1", "2"]
    assert _saved_step(run) == 2  # the last step always saves (2 is also a checkpoint step)
    first = load_checkpoint(model_path, expected=tiny())
    assert first.cfg == tiny()
    longer = TrainConfig(steps=3, checkpoint_every=2, log_every=1, workers=0)
    # state.pt holds step 2; pretend the run died after logging step 2 at 1
    state = torch.load(run / "state.pt", weights_only=True)
    state["step"] = 1
    torch.save(state, run / "state.pt")
    train(longer, run, resume=True, device="cpu", progress=False)
    rows = _rows(run)
    assert [r["step"] for r in rows] == ["1", "2", "3"]  # row 2 logged once, by the resumed run
    assert all(np.isfinite(float(r["loss"])) and float(r["loss"]) > 0 for r in rows)
    assert _saved_step(run) == 3
    second = load_checkpoint(model_path)
    changed = [k for k, v in second.state_dict().items() if not torch.equal(v, first.state_dict()[k])]
    assert changed  # the resumed steps trained


def test_init_starts_from_a_checkpoints_weights(tmp_path: Path):
    torch.manual_seed(3)
    start = PHiM(tiny())
    save_checkpoint(tmp_path / "start.pt", start)
    cfg = TrainConfig(steps=1, lr=1e-9, workers=0, log_every=1, init=str(tmp_path / "start.pt"))
    trained = load_checkpoint(train(cfg, tmp_path / "run", device="cpu", progress=False))
    pairs = list(zip(start.parameters(), trained.parameters(), strict=True))
    assert all(torch.allclose(p0, p1, atol=1e-6) for p0, p1 in pairs)  # one step at lr 1e-9 moves nothing
    fresh = PHiM(tiny())
    assert not all(
        torch.allclose(p0, p2) for p0, p2 in zip(start.parameters(), fresh.parameters(), strict=True)
    )
    other = dataclasses.replace(tiny(), buffer_sectors=2)
    save_checkpoint(tmp_path / "other.pt", PHiM(other))
    with pytest.raises(CheckpointError, match="buffer_sectors"):
        train(replace(cfg, init=str(tmp_path / "other.pt")), tmp_path / "run2", device="cpu", progress=False)


def test_a_run_without_intensity_starts_from_a_model_that_read_it(tmp_path: Path):
    """`tiny` (it reads x, y, z) with --init of a model that read intensity: the first VFE layer keeps every
    weight but the intensity column's, and the trained model evaluates on 4-column scans."""
    torch.manual_seed(3)
    cfg4 = tiny().reading(4)
    save_checkpoint(tmp_path / "start.pt", start := PHiM(cfg4))
    init = str(tmp_path / "start.pt")
    cfg = TrainConfig(steps=1, lr=1e-9, workers=0, log_every=1, init=init)
    trained = load_checkpoint(train(cfg, tmp_path / "run", device="cpu", progress=False))
    assert trained.cfg.vfe.point_features == 3
    w0, w1 = start.voxelizer.layers[0].linear.weight, trained.voxelizer.layers[0].linear.weight
    assert w0.shape[1] == w1.shape[1] + 1
    torch.testing.assert_close(w1, torch.cat([w0[:, :3], w0[:, 4:]], 1), rtol=0, atol=1e-6)
    r = predict_scan(trained, SimSource(7)(0))
    assert len(r.predictions) == trained.cfg.sectors_per_turn
    with pytest.raises(ValueError, match=r"point_features: 2; expected 0 or 3\.\.5"):
        replace(cfg, point_features=2)
    assert replace(cfg, point_features=4).model_config() == cfg4


def test_one_cycle_schedule_equals_torchs_one_cycle_lr():
    cfg = TrainConfig(steps=50, lr=2e-3)
    p = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.AdamW([p], lr=cfg.lr)
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt,
        max_lr=cfg.lr,
        total_steps=cfg.steps,
        pct_start=cfg.pct_start,
        div_factor=cfg.div_factor,
        final_div_factor=cfg.final_div_factor,
        base_momentum=0.85,
        max_momentum=0.95,
    )
    for step in range(cfg.steps):
        lr, beta1 = one_cycle(step, cfg)
        assert lr == pytest.approx(opt.param_groups[0]["lr"], rel=1e-9)
        assert beta1 == pytest.approx(opt.param_groups[0]["betas"][0], rel=1e-9)
        opt.step()
        sched.step()


def test_training_with_a_data_loader_worker_process(tmp_path: Path):
    """One step of two scans, both from the worker, which builds its object bank (two scans) and pastes from
    it into both (`fade` 1: a one-step run pastes in its step)."""
    sample = SampleConfig(gt_sampling=GTSamplingConfig(fade=1.0))
    cfg = TrainConfig(steps=1, log_every=1, workers=1, batch_size=2, sample=sample)
    train(cfg, tmp_path / "run", device="cpu", progress=False)
    assert float(_rows(tmp_path / "run")[-1]["scans_per_s"]) > 0


@pytest.mark.skipif(
    shutil.which("torchrun", path=str(Path(sys.executable).parent)) is None, reason="torchrun"
)
def test_ddp_under_torchrun_on_cpu(tmp_path: Path):
    """The same command with two processes (gloo): both ranks step together, rank 0 writes the run; a
    time budget stops both at the same step, and --resume continues."""
    torchrun = str(Path(sys.executable).parent / "torchrun")
    phim = str(Path(sys.executable).parent / "phim")
    cmd = [torchrun, "--standalone", "--nproc_per_node", "2", "--no-python", phim, "train"]
    args = [
        "--out",
        str(tmp_path / "ddp"),
        "--steps",
        "2",
        "--workers",
        "0",
        "--threads",
        "1",
        "--device",
        "cpu",  # two processes on the CPU, also on a machine with one GPU
        "--direction-weight",
        "0.5",
        "--no-progress",
    ]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    runs = (  # out of time after step 1 (both ranks), then resumed to the end
        (["--max-minutes", "0.000001"], ["1"], "stopped at step 1 of 2"),
        (["--resume"], ["1", "2"], "resuming"),
    )
    for more, logged, said in runs:
        done = subprocess.run(
            cmd + args + ["--log-every", "1", *more], capture_output=True, text=True, env=env, timeout=300
        )
        assert done.returncode == 0, done.stderr[-3000:]
        assert "DDP rank 0 of 2" in done.stderr and "DDP rank 1 of 2" in done.stderr and said in done.stderr
        assert [r["step"] for r in _rows(tmp_path / "ddp")] == logged
    assert json.loads((tmp_path / "ddp" / "train.json").read_text())["loss"]["direction_weight"] == 0.5
    load_checkpoint(tmp_path / "ddp" / "model.pt", expected=tiny())


def test_your_own_data_trains_evaluates_and_loads(tmp_path: Path):
    """The user's path: convert scans to native .npz, train on them, evaluate the run's checkpoint."""
    from lidar.readers import write_labeled

    data = tmp_path / "native"
    data.mkdir()
    for i in range(2):
        write_labeled(data / f"scan{i}.npz", SimSource(3)(i))
    cfg = TrainConfig(data=f"native:{data}", steps=2, checkpoint_every=2, log_every=1, workers=0)
    model_path = train(cfg, tmp_path / "run", device="cpu", progress=False)
    phim = str(Path(sys.executable).parent / "phim")
    args = ["eval", "--checkpoint", str(model_path), "--data", f"native:{data}", "--json"]
    done = subprocess.run([phim, *args], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert done.returncode == 0, done.stderr[-3000:]
    assert set(json.loads(done.stdout)["by_buffered_sectors"]) == {"0", "1", "2", "3"}


def test_sim_streams_are_distinct_and_reproducible():
    assert sim_seed(0, 5) == sim_seed(0, 5)
    train_seeds = {sim_seed(0, i) for i in range(2000)}
    assert not train_seeds & {sim_seed(7, i) for i in range(200)}
    a, b = SimSource(7)(3), SimSource(7)(3)
    assert a.name == "sim-7-000003" and np.array_equal(a.points, b.points)


def test_eval_scores_every_fill_level_and_predictions_round_trip(tmp_path: Path):
    torch.manual_seed(0)
    from model.detector import PHiM

    model = PHiM(tiny()).eval()
    scan = SimSource(7)(0)
    r = predict_scan(model, scan)
    assert len(r.predictions) == 4 and len(r.truths) == 4
    sizes = [len(t) for t in r.truths]
    assert sizes == sorted(sizes) and sizes[-1] == len(scan.gt)
    result = score([r])
    assert set(result) == {"LEVEL_1", "LEVEL_2", "by_buffered_sectors", "by_buffered_sectors_global"}
    for view in ("by_buffered_sectors", "by_buffered_sectors_global"):
        assert set(result[view]) == {"0", "1", "2", "3"}
        assert result["LEVEL_1"] == result[view]["3"]["LEVEL_1"]
    # the ground truth (boxes with points: Waymo drops the others) as predictions scores 1 at every fill level
    seen = [t.select(t.num_points > 0) for t in r.truths]
    perfect = ScanResult(
        r.name, [Predictions(t.boxes, np.ones(len(t), np.float32), t.labels) for t in seen], seen
    )
    scored = score([perfect])
    vehicle = CLASS_NAMES.index("VEHICLE")
    on_scene = []  # on the whole turn, a perfect partial prediction finds the share of the boxes it has seen
    for b, truth in enumerate(seen):
        present = [CLASS_NAMES[c] for c in np.unique(truth.labels)]
        assert present and all(
            scored["by_buffered_sectors"][str(b)]["LEVEL_2"][c]["AP"] == 1.0 for c in present
        )
        on_scene.append(scored["by_buffered_sectors_global"][str(b)]["LEVEL_2"]["VEHICLE"]["AP"])
        share = (truth.labels == vehicle).sum() / (seen[-1].labels == vehicle).sum()
        assert on_scene[-1] == pytest.approx(share, abs=0.03)
    assert on_scene == sorted(on_scene) and on_scene[0] < 0.6 and on_scene[-1] == 1.0
    write_predictions(tmp_path / "p.npz", [r])
    back = read_predictions(tmp_path / "p.npz")
    np.testing.assert_array_equal(back[r.name].boxes, r.predictions[-1].boxes)
    np.testing.assert_array_equal(
        read_predictions(tmp_path / "p.npz", 0)[r.name].scores, r.predictions[0].scores
    )


def test_phim_eval_command_prints_the_documented_json(tmp_path: Path):
    from model.checkpoint import save_checkpoint
    from model.detector import PHiM

    torch.manual_seed(0)
    save_checkpoint(tmp_path / "m.pt", PHiM(tiny()))
    phim = str(Path(sys.executable).parent / "phim")
    args = ["eval", "--checkpoint", str(tmp_path / "m.pt"), "--data", "sim", "--scans", "2", "--seed", "7"]
    extra = ["--json", "--predictions", str(tmp_path / "p.npz"), "--pictures", str(tmp_path / "png")]
    done = subprocess.run([phim, *args, *extra], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout)
    for top in (
        result,
        *result["by_buffered_sectors"].values(),
        *result["by_buffered_sectors_global"].values(),
    ):
        for level in ("LEVEL_1", "LEVEL_2"):
            assert set(top[level]) == {"VEHICLE", "PEDESTRIAN", "CYCLIST", "mean"}
            assert all(0.0 <= v <= 1.0 for c in top[level].values() for v in c.values())
    assert len(read_predictions(tmp_path / "p.npz")) == 2
    assert len(list((tmp_path / "png").glob("*.png"))) == 2
    rescore = [phim, "eval", "--rescore", str(tmp_path / "p.npz"), *args[3:], "--json"]
    again = subprocess.run(rescore, capture_output=True, text=True, timeout=300, cwd=REPO)
    assert again.returncode == 0, again.stderr[-3000:]
    assert json.loads(again.stdout) == result  # the file holds everything the score needs
