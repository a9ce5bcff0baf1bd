"""The model `phim serve` runs when no checkpoint is given.

Until a trained checkpoint ships, the default is the `tiny` config with freshly initialised weights from a
fixed seed (deterministic, so every worker of a deployment serves the same model). Switch `load_default_model`
to the shipped checkpoint once it exists. `python -m server.default_model --out PATH` writes it as a
checkpoint file (the Docker image bakes its weights in this way).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from model.checkpoint import save_checkpoint
from model.config import get_config, tiny
from model.detector import PHiM

DEFAULT_SEED = 0
DEFAULT_SOURCE = f"embedded default: config 'tiny', untrained weights from seed {DEFAULT_SEED}"


def load_default_model(device: str | torch.device = "cpu") -> tuple[PHiM, str]:
    """-> (the default model on `device`, a description of where its weights come from)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(DEFAULT_SEED)
        model = PHiM(tiny())
    return model.to(device).eval(), DEFAULT_SOURCE


def init_model(config: str, device: str | torch.device = "cpu") -> tuple[PHiM, str]:
    """A named config with untrained fixed-seed weights (e.g. to measure the paper config's speed)."""
    if config == "tiny":
        return load_default_model(device)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(DEFAULT_SEED)
        model = PHiM(get_config(config))
    return model.to(device).eval(), f"config {config!r}, untrained weights from seed {DEFAULT_SEED}"


def main() -> None:
    parser = argparse.ArgumentParser(description="Write the default model as a checkpoint file.")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    model, source = load_default_model("cpu")
    save_checkpoint(args.out, model, meta={"source": source})
    print(f"wrote {args.out} ({source})")


if __name__ == "__main__":
    main()
