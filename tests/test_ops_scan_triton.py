"""The selective-scan Triton kernels (model/ops/scan_triton.py) against their torch twin, on the CPU in
Triton's interpreter (TRITON_INTERPRET=1, in a process of its own: the variable must be set before the
kernels are defined). tests/test_cuda.py runs the same cases compiled on a GPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
from conftest import REPO

pytest.importorskip("triton", reason="the dev extra installs triton (its interpreter runs these tests)")
from model.ops.scan_triton import MAX_CHUNKS, chunk_length  # needs triton

TOL = 1e-5  # float32 kernels against the float64 twin


def test_chunks_grow_to_keep_the_carry_walk_short():
    assert [chunk_length(t) for t in (1, 64 * MAX_CHUNKS, 64 * MAX_CHUNKS + 1)] == [64, 64, 128]
    assert -(-300_000 // chunk_length(300_000)) <= MAX_CHUNKS


def check_cases(cases: list[dict]) -> None:
    assert len(cases) == 7
    for c in cases:
        assert c["y_err"] < TOL and c["pad_zero"], c
        assert c["final_err"] < TOL, c


def test_triton_scan_equals_its_twin_in_the_interpreter():
    env = os.environ | {"TRITON_INTERPRET": "1", "PYTHONPATH": f"{REPO}{os.pathsep}{REPO / 'tests'}"}
    run = subprocess.run(
        [sys.executable, str(REPO / "tests" / "scan_triton_cases.py"), "cpu"],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    check_cases([json.loads(line) for line in run.stdout.splitlines() if line.startswith("{")])
