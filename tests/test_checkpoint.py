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
    """How the scan is computed (implementation, chunk size) is no part of the model: any setting loads."""
    cfg = tiny()
    mamba = dataclasses.replace(cfg.backbone.mamba, scan=ScanImpl.REFERENCE, chunk_size=8)
    saved = dataclasses.replace(cfg, backbone=dataclasses.replace(cfg.backbone, mamba=mamba))
    path = tmp_path / "m.pt"
    save_checkpoint(path, PHiM(saved))
    model = load_checkpoint(path, expected=tiny())
    assert model.cfg == saved  # the file's own setting is used
    assert tiny().backbone.mamba.scan is ScanImpl.AUTO


def test_fields_added_later_take_their_defaults(tmp_path):
    """A file written before a config field existed loads, with the field's default; junk configs fail."""
    path = tmp_path / "old.pt"
    save_checkpoint(path, PHiM(paper()))  # its Mamba and head use those fields' defaults
    payload = torch.load(path, weights_only=True)
    del payload["config"]["backbone"]["mamba"]["shared_decay"]  # as written before these fields existed
    del payload["config"]["head"]["heading"]
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
