"""The model `phim serve` runs when no checkpoint is given: the shipped default.

The default is `model/weights/tiny-sim.pt`: the `tiny` config trained on the LiDAR simulator
(docs/model-card.md; `bash scripts/train_default.sh` reproduces it).
`python -m server.default_model --out PATH` writes it as a checkpoint file (the Docker image bakes its weights
in this way). `init_model` gives other configs with untrained fixed-seed weights, to measure their speed.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import torch

from model.checkpoint import DEFAULT_CHECKPOINT, load_checkpoint
from model.config import get_config, tiny
from model.detector import PHiM

DEFAULT_SEED = 0
DEFAULT_SOURCE = f"shipped default: {DEFAULT_CHECKPOINT.name} (config 'tiny', trained on the simulator)"


def load_default_model(device: str | torch.device = "cpu") -> tuple[PHiM, str]:
    """-> (the shipped default model on `device`, a description of where its weights come from)."""
    return load_checkpoint(DEFAULT_CHECKPOINT, expected=tiny(), device=device).eval(), DEFAULT_SOURCE


def init_model(config: str, device: str | torch.device = "cpu") -> tuple[PHiM, str]:
    """A named config with untrained fixed-seed weights (e.g. to measure the paper config's speed)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(DEFAULT_SEED)
        model = PHiM(get_config(config))
    return model.to(device).eval(), f"config {config!r}, untrained weights from seed {DEFAULT_SEED}"


def main() -> None:
    parser = argparse.ArgumentParser(description="Write the default model as a checkpoint file.")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    load_default_model("cpu")  # fails loudly if the shipped file is missing or does not fit
    args.out.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(DEFAULT_CHECKPOINT, args.out)
    print(f"wrote {args.out} ({DEFAULT_SOURCE})")


if __name__ == "__main__":
    main()
