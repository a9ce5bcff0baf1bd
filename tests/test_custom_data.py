"""`--data custom:DIR` (OpenPCDet's custom layout, lidar/custom.py): the reader, its errors (file and
line named), the class map, the splits, and the user's path: fine-tune the shipped default on a folder written
from simulated scans, its loss falls, and `phim serve` serves the result."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import httpx
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from server_helpers import sector_msg, serve

from contract import MSGPACK, DetectionsReply, decode_response, encode_sector
from lidar.custom import (
    CustomDataError,
    read_custom_labels,
    read_custom_points,
    read_custom_scan,
    write_custom_scan,
    write_splits,
)
from lidar.datasets import parse_data_spec
from lidar.readers import sector_of_xy
from lidar.selection import ClassMap, Split, parse_class_map
from lidar.sim import Sensor, SimConfig
from lidar.sources import SimSource, iter_labeled, scan_source
from lidar.types import GroundTruth, LabeledScan
from model.checkpoint import (
    DEFAULT_CHECKPOINT,
    init_weights,
    load_checkpoint,
    read_checkpoint,
    save_checkpoint,
)
from model.config import CLASS_NAMES, tiny
from model.detector import PHiM
from model.train.data import AugmentConfig, SampleConfig, make_sample
from model.train.loop import TrainConfig, train
from model.train.loss import LossConfig
from model.train.step import TrainStep
from phim.cli import main as app

KITTI_NAMES = ("Car", "Pedestrian", "Cyclist")  # written for VEHICLE, PEDESTRIAN, CYCLIST
KITTI_MAP = "Car=VEHICLE,Pedestrian=PEDESTRIAN,Cyclist=CYCLIST"
RANGE_M = 20.0  # the test's scans are cut to this range (and every 3rd point): quick training steps


def small_scan(scan: LabeledScan, grow: float = 1.0) -> LabeledScan:
    """A simulated scan within RANGE_M, every 3rd point, with the boxes centred 2 m inside that range, their
    sizes times `grow`."""
    p, gt = scan.points, scan.gt
    keep = (np.hypot(p[:, 0], p[:, 1]) < RANGE_M) & (np.arange(len(p)) % 3 == 0)  # (N,)
    near = np.hypot(gt.boxes[:, 0], gt.boxes[:, 1]) < RANGE_M - 2.0  # (M,)
    boxes = gt.boxes[near].copy()  # (M', 7)
    boxes[:, 3:6] *= grow
    truth = GroundTruth.from_boxes(boxes, gt.labels[near], p[keep])
    return dataclasses.replace(scan, points=p[keep], gt=truth, time=None, sector=None)


def write_folder(root: Path, scans: list[LabeledScan], splits: dict[Split, list[str]] | None = None) -> Path:
    for scan in scans:
        write_custom_scan(root, scan, KITTI_NAMES)
    if splits:
        write_splits(root, splits)
    return root


def folder_with_labels(tmp_path: Path, text: str) -> Path:
    """A one-scan custom folder whose label file holds `text`; returns that label file."""
    rng = np.random.default_rng(0)
    (tmp_path / "points").mkdir(parents=True)
    (tmp_path / "labels").mkdir()
    points = np.column_stack([rng.uniform(-20, 20, (100, 3)), rng.uniform(0, 1, 100)]).astype(np.float32)
    np.save(tmp_path / "points" / "a.npy", points)
    (tmp_path / "labels" / "a.txt").write_text(text)
    return tmp_path / "labels" / "a.txt"


def test_a_folder_written_from_sim_scans_reads_back_as_them(tmp_path: Path):
    scans = [SimSource(5, SimConfig(sensor=Sensor.HDL32E))(i) for i in range(2)]
    write_folder(tmp_path, scans)
    back = list(iter_labeled(f"custom:{tmp_path}", classes=parse_class_map(KITTI_MAP)))
    assert [s.name for s in back] == [s.name for s in scans]  # no ImageSets: every scan, by name
    for mine, theirs in zip(back, scans, strict=True):
        np.testing.assert_array_equal(mine.points, theirs.points[:, :4])
        assert mine.fields == ("x", "y", "z", "intensity")
        np.testing.assert_array_equal(mine.gt.labels, theirs.gt.labels)
        np.testing.assert_allclose(mine.gt.boxes[:, :6], theirs.gt.boxes[:, :6], atol=1e-5)
        turn = np.angle(np.exp(1j * (mine.gt.boxes[:, 6] - theirs.gt.boxes[:, 6])))  # headings wrapped
        np.testing.assert_allclose(turn, 0.0, atol=1e-5)
        assert np.all(mine.gt.boxes[:, 6] >= -np.pi) and np.all(mine.gt.boxes[:, 6] < np.pi)
        assert abs(int(mine.gt.num_points.sum()) - int(theirs.gt.num_points.sum())) <= 3  # 1e-6 m rounding
        np.testing.assert_array_equal(mine.sector, sector_of_xy(mine.points[:, 0], mine.points[:, 1], 4))


def test_splits_pick_the_scans_of_each_command(tmp_path: Path):
    scans = [small_scan(SimSource(5)(i)) for i in range(3)]
    names = [s.name for s in scans]
    write_folder(tmp_path, scans)
    spec, classes = f"custom:{tmp_path}", parse_class_map(KITTI_MAP)

    def read(split: Split) -> list[str]:
        return [s.name for s in iter_labeled(spec, split=split, classes=classes)]

    assert read(Split.TRAIN) == read(Split.VAL) == names  # no ImageSets: all, sorted
    write_splits(tmp_path, {Split.TRAIN: [names[2], names[0]], Split.VAL: [names[1]]})
    assert read(Split.TRAIN) == [names[2], names[0]] and read(Split.VAL) == [names[1]]
    (tmp_path / "ImageSets" / "val.txt").write_text(f"{names[1]}\n\nnot-there\n")
    with pytest.raises(CustomDataError, match=r"ImageSets/val\.txt:3: 'not-there' has no points file"):
        read(Split.VAL)
    with pytest.raises(FileNotFoundError, match=r"lacks \['points', 'labels'\]; expected OpenPCDet"):
        list(iter_labeled(f"custom:{tmp_path / 'points'}"))


def test_class_map_maps_ignores_and_refuses(tmp_path: Path):
    labels = folder_with_labels(
        tmp_path, "# x y z dx dy dz heading class\n1 2 -1 4 2 1.5 0.5 Car\n\n3 4 -1 0.6 0.6 1.7 0 Misc\n"
    )
    not_mapped = rf"{labels}:2: class 'Car' is not in the class map .*--class-map"
    with pytest.raises(CustomDataError, match=not_mapped):
        read_custom_labels(labels, ClassMap())
    with pytest.raises(CustomDataError, match=rf"{labels}:4: class 'Misc'"):
        read_custom_labels(labels, parse_class_map("car=vehicle"))
    boxes, classes = read_custom_labels(labels, parse_class_map("Car=VEHICLE,Misc=IGNORE"))
    assert classes.tolist() == [CLASS_NAMES.index("VEHICLE")] and boxes.shape == (1, 7)
    ignore_rest = parse_class_map("Car=VEHICLE,*=IGNORE")
    assert str(ignore_rest) == "Car=VEHICLE,*=IGNORE" and parse_class_map(str(ignore_rest)) == ignore_rest
    np.testing.assert_array_equal(read_custom_labels(labels, ignore_rest)[0], boxes)
    assert parse_class_map("").table()["vehicle"] == 0  # PHiM's names (OpenPCDet's Vehicle, ...) as they are
    for bad, said in (
        ("Car", "expected NAME=CLASS"),
        ("Car=TRUCK", "expected NAME=CLASS"),
        ("*=VEHICLE", r"only \*=IGNORE"),
        ("Car=VEHICLE,car=CYCLIST", "mapped twice"),
    ):
        with pytest.raises(ValueError, match=said):
            parse_class_map(bad)
    with pytest.raises(ValueError, match="custom:DIR data only"):
        scan_source("sim", 0, classes=ignore_rest)
    with pytest.raises(ValueError, match="custom:DIR data only"):
        TrainConfig(data="sim", class_map="Car=VEHICLE")


@pytest.mark.parametrize(
    ("line", "said"),
    [
        ("1 2 3 4 5 6 Car", "7 columns, expected 8: x y z dx dy dz heading class"),
        ("1 2 3 4 5 6 0.1 Car extra", "9 columns"),
        ("1 2 three 4 5 6 0.1 Car", "a non-number"),
        ("1 2 3 -4 5 6 0.1 Car", "box size dx dy dz .* must be positive"),
        ("1 2 3 4 0 6 0.1 Car", "box size .* must be positive"),
        ("1 2 nan 4 5 6 0.1 Car", "NaN or infinity"),
        ("1 2 3 4 5 6 inf Car", "NaN or infinity"),
        ("1 2 3 4 5 6 0.1", "7 columns"),
    ],
)
def test_a_bad_label_line_is_named_by_file_and_line(tmp_path: Path, line: str, said: str):
    labels = folder_with_labels(tmp_path, f"1 2 -1 4 2 1.5 0.5 Car\n{line}\n")
    with pytest.raises(CustomDataError, match=rf"^{labels}:2: {said}"):
        read_custom_labels(labels, parse_class_map(KITTI_MAP))
    with pytest.raises(CustomDataError, match=rf"{labels}:2: {said}"):  # before any scan is read
        scan_source(f"custom:{tmp_path}", 0, classes=parse_class_map(KITTI_MAP))
    labels.write_bytes(b"1 2 3 4 5 6 0.1 Car\n\xff\xfe\n")
    with pytest.raises(CustomDataError, match=rf"^{labels}: not a UTF-8 text file"):
        read_custom_labels(labels, parse_class_map(KITTI_MAP))


@pytest.mark.parametrize(
    ("points", "said"),
    [
        (np.zeros((10, 4), np.float64), "dtype float64, expected float32"),
        (np.zeros((10, 3), np.float32), r"shape \(10, 3\), expected \(N, 4\+\)"),
        (np.zeros(40, np.float32), r"shape \(40,\)"),
        (np.array([[0, 0, 0, 0.5], [1, np.nan, 0, 0.5]], np.float32), "1 of 2 points have a NaN .*row 1"),
        (np.array([[0, 0, 0, 0.5], [1, 1, 0, 200.0]], np.float32), r"intensity \(the 4th col.* 0.5..200"),
    ],
)
def test_a_bad_points_file_is_named(tmp_path: Path, points: np.ndarray, said: str):
    folder_with_labels(tmp_path, "")
    path = tmp_path / "points" / "a.npy"
    np.save(path, points)
    with pytest.raises(CustomDataError, match=rf"^{path}: {said}"):
        read_custom_points(path)
    runner = CliRunner()
    done = runner.invoke(app, ["eval", "--data", f"custom:{tmp_path}", "--scans", "1"])
    assert done.exit_code == 2 and str(path) in done.output, done.output  # a usage error, before any model
    path.write_bytes(b"not numpy")
    with pytest.raises(CustomDataError, match=rf"^{path}: not a numpy .npy array"):
        read_custom_scan(path, ClassMap())


def test_commands_refuse_bad_data_before_they_run(tmp_path: Path):
    labels = folder_with_labels(tmp_path, "1 2 -1 4 2 1.5 0.5 Truck\n")
    runner = CliRunner()
    out = str(tmp_path / "run")
    done = runner.invoke(app, ["train", "--data", f"custom:{tmp_path}", "--out", out, "--steps", "1"])
    assert done.exit_code == 2 and f"{labels}:1: class 'Truck'" in done.output, done.output
    assert not (tmp_path / "run").exists()
    done = runner.invoke(app, ["eval", "--data", f"custom:{tmp_path}", "--class-map", "Truck"])
    assert done.exit_code == 2 and "expected NAME=CLASS" in done.output, done.output
    done = runner.invoke(app, ["diagnose", "--data", "sim", "--class-map", "Truck=VEHICLE"])
    assert done.exit_code == 2 and "custom:DIR data only" in done.output, done.output
    (labels.parent / "a.txt").unlink()
    done = runner.invoke(app, ["eval", "--data", f"custom:{tmp_path}"])
    assert done.exit_code == 2 and "no label file" in done.output, done.output
    assert parse_data_spec(f"custom:{tmp_path}").path == tmp_path


FIXED = SampleConfig(  # each scan as it is: no augmentation, sector 0 first, no pasted objects
    augment=AugmentConfig(
        rotate=False, flip=False, scale=(1.0, 1.0), intensity_gain=(1.0, 1.0), constant_intensity=0.0
    ),
    random_start=False,
    clockwise=0.0,
    gt_sampling=None,
)


def batch_loss(model: PHiM, scans: list[LabeledScan]) -> float:
    """The training loss of `scans` as one batch (FIXED samples, every buffer fill level), as a training
    step computes it (batch norms on the batch), without gradients."""
    model.train()
    with torch.no_grad():
        batch = [make_sample(s, model.cfg, FIXED, np.random.default_rng(0)) for s in scans]
        return float(TrainStep(model, LossConfig())(batch).total)


def test_fine_tuning_the_default_on_a_custom_folder_lowers_its_loss_and_serves(tmp_path: Path):
    """The recipe of docs/training.md at toy size, on two small scans of the 32-beam preset whose labels are
    drawn 20 % larger than the simulator's (an annotation convention the default does not know): `phim train
    --init default --data custom:DIR --class-map ...` runs; the same loop started from the default with both
    scans in every step (no augmentation: the step's loss is the loss measured) lowers their loss; `phim
    serve` serves the result."""
    sim = SimSource(5, SimConfig(sensor=Sensor.HDL32E))
    scans = [small_scan(sim(i), grow=1.2) for i in range(2)]
    assert all(len(s.gt) >= 5 for s in scans)
    data = write_folder(tmp_path / "custom", scans, {Split.TRAIN: [s.name for s in scans]})
    args = ["train", "--init", "default", "--data", f"custom:{data}", "--class-map", KITTI_MAP]
    args += ["--out", str(tmp_path / "cli"), "--steps", "1", "--workers", "0", "--no-progress"]
    done = CliRunner().invoke(app, args)
    assert done.exit_code == 0, done.output
    assert read_checkpoint(tmp_path / "cli" / "model.pt")["meta"]["train"]["class_map"] == KITTI_MAP

    spec = f"custom:{data}"
    cfg = TrainConfig(data=spec, class_map=KITTI_MAP, init=str(DEFAULT_CHECKPOINT), sample=FIXED)
    cfg = dataclasses.replace(cfg, steps=3, batch_size=2, lr=2e-4, workers=0, log_every=1)
    tuned_path = train(cfg, tmp_path / "run", device="cpu", progress=False)
    read_back = list(iter_labeled(spec, classes=parse_class_map(KITTI_MAP)))
    start = PHiM(tiny())
    start.load_state_dict(init_weights(DEFAULT_CHECKPOINT, tiny()))
    before, after = batch_loss(start, read_back), batch_loss(load_checkpoint(tuned_path), read_back)
    assert after < 0.97 * before, (before, after)

    points = read_back[0].points
    sector = points[sector_of_xy(points[:, 0], points[:, 1], 4) == 0]
    with serve(None, checkpoint=tuned_path) as server:
        model = httpx.get(f"{server.url}/v1/model", timeout=10).json()
        assert model["weights"] == f"checkpoint {tuned_path}"
        r = httpx.post(
            f"{server.url}/v1/streams/car-1/sectors",
            content=encode_sector(sector_msg("car-1", 0, sector, index=0)),
            headers={"Content-Type": MSGPACK},
            timeout=60,
        )
    reply = decode_response(r.content)
    assert r.status_code == 200 and isinstance(reply, DetectionsReply), reply
    assert reply.stream_id == "car-1" and reply.seq == 0


def test_eval_without_the_refiner_scores_the_detector_alone(tmp_path: Path):
    """`phim eval --no-refiner` of the default scores what a checkpoint of its detector alone scores: the
    like-for-like baseline of a fine-tuned detector (docs/training.md)."""
    write_folder(tmp_path / "custom", [small_scan(SimSource(5, SimConfig(sensor=Sensor.HDL32E))(0))])
    default = load_checkpoint(DEFAULT_CHECKPOINT)
    assert default.refiner is not None
    detector = PHiM(dataclasses.replace(default.cfg, refine=None))
    detector.load_state_dict({k: v for k, v in default.state_dict().items() if not k.startswith("refiner.")})
    save_checkpoint(tmp_path / "detector.pt", detector)
    args = ["eval", "--data", f"custom:{tmp_path / 'custom'}", "--class-map", KITTI_MAP, "--json"]

    def scored(*more: str) -> dict:
        done = CliRunner().invoke(app, [*args, *more])
        assert done.exit_code == 0, done.output
        return json.loads(done.stdout)

    alone = scored("--checkpoint", "default", "--no-refiner")
    assert alone == scored("--checkpoint", str(tmp_path / "detector.pt"))
    assert alone != scored("--checkpoint", "default")


def test_train_refiner_reads_a_custom_folder(tmp_path: Path):
    """`phim train-refiner --data custom:DIR --class-map ...` fits the refiner on the folder's training scans
    (one pass, however many seeds: a second stream would read the same files) and records where from."""
    scans = [small_scan(SimSource(5, SimConfig(sensor=Sensor.HDL32E))(i)) for i in range(2)]
    data = write_folder(tmp_path / "custom", scans, {Split.TRAIN: [s.name for s in scans]})
    out = tmp_path / "refined.pt"
    args = ["train-refiner", "--data", f"custom:{data}", "--class-map", KITTI_MAP, "--out", str(out)]
    done = CliRunner().invoke(app, [*args, "--seed", "1", "--seed", "2", "--epochs", "1", "--threads", "1"])
    assert done.exit_code == 0, done.output
    assert "from the boxes of 1 x 2 scans of custom:" in done.output and "stage 2: " in done.output
    meta = read_checkpoint(out)["meta"]["refiner"]
    assert meta["data"] == f"custom:{data}" and meta["seeds"] == [1] and meta["scans"] == 2
    assert load_checkpoint(out).refiner is not None
    missing = f"custom:{tmp_path / 'none'}"
    bad = CliRunner().invoke(app, ["train-refiner", "--data", missing, "--out", str(out)])
    assert bad.exit_code == 2 and "--data" in bad.output
