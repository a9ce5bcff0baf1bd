"""`python -m server.default_model --out PATH`: the model `phim serve` runs when no checkpoint is given (the
shipped default, `model.checkpoint.load_default_model`) written as a checkpoint file; the Docker image bakes
its weights in this way."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from model.checkpoint import DEFAULT_CHECKPOINT, DEFAULT_SOURCE, load_default_model


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
