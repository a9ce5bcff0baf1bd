from __future__ import annotations

import dataclasses

import pytest
import torch

from model.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from model.config import HeadingCode, PHiMConfig, ScanImpl, get_config, paper, tiny
from model.detector import PHiM


def test_roundtrip_is_bit_exact(tmp_path):
    model = PHiM(tiny())
    for p in model.parameters():
        p.data.normal_()
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, meta={"note": "test"})
    loaded = load_checkpoint(path, expected=tiny())
    ref = model.state_dict()
    got = loaded.state_dict()
    assert ref.keys() == got.keys()
    for k in ref:
        assert torch.equal(ref[k], got[k]), k
    assert loaded.cfg == model.cfg


def test_config_roundtrip():
    for cfg in (tiny(), paper()):
        assert PHiMConfig.from_dict(cfg.to_dict()) == cfg
    mamba = get_config("tiny").backbone.mamba
    assert (mamba.d_state, mamba.expand, mamba.shared_decay) == (4, 1, True)
    assert get_config("tiny").head.heading is HeadingCode.AXIS_DIRECTION


def test_mismatch_names_the_field(tmp_path):
    path = tmp_path / "m.pt"
    save_checkpoint(path, PHiM(tiny()))
    other = dataclasses.replace(tiny(), buffer_sectors=2)
    with pytest.raises(CheckpointError, match="buffer_sectors: checkpoint has 3, expected 2"):
        load_checkpoint(path, expected=other)
    deeper = dataclasses.replace(tiny(), backbone=dataclasses.replace(tiny().backbone, d_model=48))
    with pytest.raises(CheckpointError, match=r"backbone\.d_model"):
        load_checkpoint(path, expected=deeper)


def test_scan_settings_are_not_a_mismatch(tmp_path):
    """How the scan is computed (implementation, chunk size) and the graph engine's sector_voxels are no
    part of the model: any setting loads."""
    cfg = tiny()
    mamba = dataclasses.replace(cfg.backbone.mamba, scan=ScanImpl.REFERENCE, chunk_size=8)
    saved = dataclasses.replace(cfg, backbone=dataclasses.replace(cfg.backbone, mamba=mamba))
    path = tmp_path / "m.pt"
    save_checkpoint(path, PHiM(saved))
    model = load_checkpoint(path, expected=tiny())
    assert model.cfg == saved  # the file's own setting is used
    assert tiny().backbone.mamba.scan is ScanImpl.AUTO
    roomy = dataclasses.replace(tiny(), sector_voxels=20000)  # the graph engine's rows: no part of the model
    save_checkpoint(path, PHiM(roomy))
    assert load_checkpoint(path, expected=tiny()).cfg.sector_voxels == 20000


def test_fields_added_later_take_their_defaults(tmp_path):
    """A file written before a config field existed loads, with the field's default; junk configs fail."""
    path = tmp_path / "old.pt"
    save_checkpoint(path, PHiM(paper()))  # its Mamba and head use those fields' defaults
    payload = torch.load(path, weights_only=True)
    del payload["config"]["backbone"]["mamba"]["shared_decay"]  # as written before these fields existed
    del payload["config"]["head"]["heading"]
    del payload["config"]["sector_voxels"]  # the named config's (paper: 24,576), not the field's default
    torch.save(payload, path)
    model = load_checkpoint(path, expected=paper())
    assert model.cfg == paper() and model.cfg.backbone.mamba.shared_decay is False
    assert model.cfg.head.heading is HeadingCode.SIN_COS
    payload["config"]["backbone"]["mamba"]["no_such_field"] = 1
    torch.save(payload, path)
    with pytest.raises(CheckpointError, match="config unreadable"):
        load_checkpoint(path)


def test_bad_files(tmp_path):
    with pytest.raises(CheckpointError, match="no such file"):
        load_checkpoint(tmp_path / "missing.pt")
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="unreadable"):
        load_checkpoint(junk)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(1)}, other)
    with pytest.raises(CheckpointError, match="not a phim-checkpoint"):
        load_checkpoint(other)


def test_init_weights_leave_out_the_columns_a_model_does_not_read(tmp_path):
    """A model started from a checkpoint that read intensity, reading x, y, z only, detects as the
    checkpoint's model does with the intensity column zero; any other config difference is refused."""
    from test_streaming import assert_same_detections, make_model

    from lidar.synthetic import synthetic_turn
    from model.checkpoint import init_weights
    from model.sectors import split_turn
    from model.stream import StreamingDetector

    four = make_model(tiny().reading(4))
    save_checkpoint(tmp_path / "four.pt", four)
    three = PHiM(four.cfg.reading(3))
    three.load_state_dict(init_weights(tmp_path / "four.pt", three.cfg))
    turn = torch.from_numpy(synthetic_turn(seed=3))
    assert bool((turn[:, 3] != 0).any())
    zeroed = turn.clone()
    zeroed[:, 3] = 0.0
    detections = []
    for model, points in ((four, zeroed), (three, turn), (four, turn)):
        det = StreamingDetector(model.eval())
        states = [det.new_state()]
        for sector in split_turn(points, model.cfg.sectors_per_turn):
            results, states = det.step([sector], states)
        detections.append(results[0].detections)
    assert len(detections[0]) > 0
    assert_same_detections(detections[1], detections[0])
    assert not torch.equal(detections[2].scores, detections[0].scores)  # the intensity mattered to `four`
    with pytest.raises(CheckpointError, match="point_features: checkpoint has 4, expected at least 5"):
        init_weights(tmp_path / "four.pt", four.cfg.reading(5))
    with pytest.raises(CheckpointError, match="buffer_sectors"):
        init_weights(tmp_path / "four.pt", dataclasses.replace(three.cfg, buffer_sectors=2))
