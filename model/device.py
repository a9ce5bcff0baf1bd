"""Which torch device a command or the server runs on."""

from __future__ import annotations

import torch


def pick_device(name: str) -> torch.device:
    """'auto' -> cuda if available else cpu; otherwise the named device, which must exist."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but CUDA is not available")
    return dev
