"""Checkpoints: weights together with the config that built them.

File layout (torch.save of plain data, loadable with weights_only=True, never arbitrary pickles):
    {"format": "phim-checkpoint", "version": 1, "config": PHiMConfig as plain dict,
     "state_dict": {...}, "meta": {...free-form plain data...}}
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from model.config import PHiMConfig, get_config, tiny
from model.detector import PHiM

FORMAT = "phim-checkpoint"
# the shipped default model (docs/model-card.md); `--checkpoint default` names it
DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "weights" / "tiny-sim.pt"
VERSION = 1
DEFAULT_SEED = 0  # of the untrained weights a named config is served with (`init_model`)
DEFAULT_SOURCE = f"shipped default: {DEFAULT_CHECKPOINT.name} (config 'tiny', trained on the simulator)"


class CheckpointError(ValueError):
    pass


def plain_config(cfg: PHiMConfig) -> dict[str, Any]:
    """Config as JSON-able plain data (enums as strings, tuples as lists)."""
    return json.loads(json.dumps(cfg.to_dict()))


def save_checkpoint(path: str | Path, model: PHiM, meta: dict[str, Any] | None = None) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "config": plain_config(model.cfg),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "meta": meta or {},
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


# how the model runs, not what it computes (the selective scan's implementation, the fixed-shape step's
# rows per buffered sector, the ego vehicle's footprint and its fields): a checkpoint loads under any of these
EXECUTION_FIELDS = frozenset({"backbone.mamba.scan", "backbone.mamba.chunk_size", "sector_voxels", "ego"})


def config_diff(a: dict[str, Any], b: dict[str, Any], prefix: str = "") -> list[str]:
    """Dotted field names whose values differ between two plain config dicts (EXECUTION_FIELDS aside)."""
    out = []
    for key in sorted(set(a) | set(b)):
        name = f"{prefix}{key}"
        if name in EXECUTION_FIELDS or name.split(".")[0] in EXECUTION_FIELDS:
            continue
        va, vb = a.get(key), b.get(key)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += config_diff(va, vb, name + ".")
        elif va != vb:
            out.append(f"{name}: checkpoint has {va!r}, expected {vb!r}")
    return out


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: no such file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises several types for corrupt files
        raise CheckpointError(f"checkpoint {path}: unreadable ({e})") from e
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path}: not a {FORMAT} file")
    if payload.get("version") != VERSION:
        raise CheckpointError(f"checkpoint {path}: version {payload.get('version')}, expected {VERSION}")
    return payload


def load_checkpoint(
    path: str | Path, expected: PHiMConfig | None = None, device: str | torch.device = "cpu"
) -> PHiM:
    """Build the model from the checkpoint's own config and load its weights.

    With `expected`, a checkpoint whose config differs raises CheckpointError naming every differing field
    (its box refiner, `refine`, aside: `tiny` with a refiner is still `tiny`).
    """
    payload = read_checkpoint(path)
    try:  # config fields added after the file was written take their defaults
        cfg = PHiMConfig.from_dict(payload["config"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint {path}: config unreadable ({type(e).__name__}: {e})") from e
    if expected is not None:  # a box refiner comes with the checkpoint's weights: not a mismatch
        diff = config_diff(plain_config(cfg), plain_config(replace(expected, refine=cfg.refine)))
        if diff:
            raise CheckpointError(f"checkpoint {path}: config mismatch: " + "; ".join(diff))
    model = PHiM(cfg)
    try:
        result = model.load_state_dict(payload["state_dict"], strict=False)
    except RuntimeError as e:  # shape mismatches
        raise CheckpointError(f"checkpoint {path}: weights do not fit config {cfg.name!r}: {e}") from e
    if result.missing_keys or result.unexpected_keys:
        raise CheckpointError(
            f"checkpoint {path}: weights do not fit config {cfg.name!r}: "
            f"missing {result.missing_keys[:5]}, unexpected {result.unexpected_keys[:5]}"
        )
    return model.to(device)


# the first VFE layer's weight (hidden, P + 9): the P raw point columns come first (model/layers/voxelize.py)
VFE_INPUT = "voxelizer.layers.0.linear.weight"


def init_weights(path: str | Path, cfg: PHiMConfig) -> dict[str, torch.Tensor]:
    """The weights of checkpoint `path` as the start of a model of config `cfg`. The checkpoint's config must
    be cfg's, but for reading more point columns (`vfe.point_features`): the weights of the columns cfg does
    not read are left out, so the new model starts as the old one with those columns zero. A box refiner's
    weights are left out too: `phim train` trains the detector, `phim train-refiner` the refiner after it."""
    model = load_checkpoint(path)
    have, want = model.cfg.vfe.point_features, cfg.vfe.point_features
    expected = replace(cfg.reading(have), refine=model.cfg.refine)
    diff = config_diff(plain_config(model.cfg), plain_config(expected))
    if want > have:
        diff.append(f"vfe.point_features: checkpoint has {have}, expected at least {want}")
    if diff:
        raise CheckpointError(f"checkpoint {path}: config mismatch: " + "; ".join(diff))
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("refiner.")}
    w = state[VFE_INPUT]  # (hidden, have + 9)
    state[VFE_INPUT] = torch.cat([w[:, :want], w[:, have:]], 1)  # (hidden, want + 9)
    return state


def checkpoint_path(name: str | Path) -> Path:
    """'default' (the shipped model) or a checkpoint path -> its path; a missing default is an error."""
    if str(name) != "default":
        return Path(name)
    if not DEFAULT_CHECKPOINT.is_file():
        raise CheckpointError(f"the default checkpoint {DEFAULT_CHECKPOINT} is missing from this install")
    return DEFAULT_CHECKPOINT


def resolve_checkpoint(name: str | Path, device: str | torch.device = "cpu") -> tuple[PHiM, Path]:
    """'default' (the shipped model) or a checkpoint path -> (the model on `device`, eval mode; its path)."""
    path = checkpoint_path(name)
    return load_checkpoint(path, device=device).eval(), path


def load_default_model(device: str | torch.device = "cpu") -> tuple[PHiM, str]:
    """-> (the shipped default model on `device`, a description of where its weights come from). The
    default is the `tiny` config trained on the LiDAR simulator (docs/model-card.md;
    `bash scripts/train_default.sh` reproduces it)."""
    return load_checkpoint(DEFAULT_CHECKPOINT, expected=tiny(), device=device).eval(), DEFAULT_SOURCE


def init_model(config: str, device: str | torch.device = "cpu") -> tuple[PHiM, str]:
    """A named config with untrained fixed-seed weights (e.g. to measure the paper config's speed)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(DEFAULT_SEED)
        model = PHiM(get_config(config))
    return model.to(device).eval(), f"config {config!r}, untrained weights from seed {DEFAULT_SEED}"
