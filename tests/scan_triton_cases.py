"""Cases for the selective-scan Triton kernels against their torch twin, run in a process of its own (tests/
test_ops_scan_triton.py sets TRITON_INTERPRET=1 there, so the kernels run on the CPU in Triton's
interpreter; on a CUDA machine without it they run on the GPU). Prints one JSON line per case."""

from __future__ import annotations

import json
import sys

import torch

from model.graph.segments import stream_segments
from model.ops.scan_torch import selective_scan_chunked
from model.ops.scan_triton import selective_scan_triton
from model.ops.segments import Segments


def _random_segments(T: int, valid_tokens: int, p_start: float, gen: torch.Generator) -> Segments:
    """Frustum-like pack: real tokens cut at random starts, padding after; no carried state."""
    valid = torch.arange(T) < valid_tokens
    start = (torch.rand(T, generator=gen) < p_start) | ~valid
    start[0] = True
    return Segments(start, valid, torch.zeros(T, dtype=torch.int64), torch.zeros(0, dtype=torch.int64))


def _streams(lengths: list[int], pad: int, gen: torch.Generator) -> Segments:
    S = len(lengths)
    real = torch.repeat_interleave(torch.arange(S), torch.tensor(lengths))
    batch = torch.cat([real, torch.randint(0, S, (pad,), generator=gen)])
    return stream_segments(batch, torch.arange(batch.numel()) < real.numel(), S)


def run_case(name: str, segs: Segments, D: int, N: int, shared: bool, with_h0: bool, device: str) -> dict:
    gen = torch.Generator().manual_seed(len(name) * 7 + D)
    T, S = segs.total, segs.num_streams
    u, B, C = (torch.randn(T, k, generator=gen, dtype=torch.float64) for k in (D, N, N))
    delta = torch.rand(T, D, generator=gen, dtype=torch.float64)
    delta[~segs.valid] = -50.0  # garbage on padding: must not reach a real token
    A = -torch.rand(D, 1 if shared else N, generator=gen, dtype=torch.float64) * 4
    h0 = torch.randn(S, D, N, generator=gen, dtype=torch.float64) if with_h0 else None
    y_ref, fin_ref = selective_scan_chunked(u, delta, A, B, C, segs, h0)
    on_dev = Segments(*(t.to(device) for t in (segs.start, segs.valid, segs.seg, segs.last)))
    args = [t.float().to(device) for t in (u, delta, A, B, C)]
    y, fin = selective_scan_triton(*args, on_dev, None if h0 is None else h0.float().to(device))
    out = {"case": name, "y_err": _rel(y, y_ref), "pad_zero": bool((y.cpu()[~segs.valid] == 0).all())}
    out["final_err"] = _rel(fin, fin_ref) if fin_ref.numel() else float(fin.numel())  # from zeros without h0
    return out


def _rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    a = a.detach().cpu().double()
    if not torch.isfinite(a).all():
        return float("inf")
    return float((a - ref).norm() / ref.norm().clamp_min(1e-30))


def cases(device: str) -> list[dict]:
    gen = torch.Generator().manual_seed(0)
    lengths = [5, 0, 70, 1, 2, 137, 3, 0, 11]  # empty streams, one longer than two chunks of 64
    out = []
    for shared in (False, True):
        for with_h0 in (False, True):
            name = f"streams shared={shared} h0={with_h0}"
            out.append(run_case(name, _streams(lengths, 9, gen), 16, 4, shared, with_h0, device))
    out.append(run_case("frustums", _random_segments(300, 271, 0.05, gen), 24, 8, False, False, device))
    out.append(run_case("one segment", _random_segments(200, 200, 0.0, gen), 8, 16, False, False, device))
    out.append(run_case("padding only", _streams([0, 0], 5, gen), 8, 4, False, True, device))
    return out


if __name__ == "__main__":
    for c in cases(sys.argv[1] if len(sys.argv) > 1 else "cpu"):
        print(json.dumps(c))
