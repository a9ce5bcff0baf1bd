"""scripts/setup.sh (run by scripts/serve.sh, scripts/test.sh and .ci/run) skips pip when the venv is current:
its stamp holds the hash of pyproject.toml, constraints.txt and the script; anything else runs pip again.

The venv here is a folder whose `bin/python` only writes down how it was called (and fails, as a pip that
could not install): so the test sees whether the script would have run pip, without installing anything."""

from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
STAMP = ".phim-setup-stamp"


def current_hash() -> str:
    files = ("pyproject.toml", "constraints.txt", "scripts/setup.sh")
    return hashlib.sha256(b"".join((REPO / f).read_bytes() for f in files)).hexdigest()


def recording_venv(tmp_path: Path) -> tuple[Path, Path]:
    venv, calls = tmp_path / "venv", tmp_path / "calls.txt"
    (venv / "bin").mkdir(parents=True)
    python = venv / "bin" / "python"
    python.write_text(f'#!/bin/sh\necho "$@" >>"{calls}"\nexit 1\n')
    python.chmod(0o755)
    return venv, calls


def setup(venv: Path, **env: str) -> subprocess.CompletedProcess[str]:
    cmd = ["bash", str(REPO / "scripts" / "setup.sh")]
    return subprocess.run(cmd, env={"PATH": "/usr/bin:/bin", "PHIM_VENV": str(venv), **env}, text=True,
                          capture_output=True, timeout=60)  # fmt: skip


def test_a_current_venv_skips_pip(tmp_path: Path) -> None:
    venv, calls = recording_venv(tmp_path)
    (venv / STAMP).write_text(current_hash() + "\n")
    r = setup(venv)
    assert r.returncode == 0, r.stderr
    assert not calls.exists()  # pip never ran
    assert (venv / STAMP).read_text().strip() == current_hash()


def test_a_changed_dependency_or_a_forced_setup_runs_pip_again(tmp_path: Path) -> None:
    venv, calls = recording_venv(tmp_path)
    for stamp, env in (("an older hash\n", {}), (current_hash() + "\n", {"PHIM_SETUP_FORCE": "1"})):
        (venv / STAMP).write_text(stamp)
        r = setup(venv, **env)
        assert r.returncode != 0  # the recording python fails as pip would
        assert "-m pip install" in calls.read_text()
        assert not (venv / STAMP).exists()  # a failed install leaves no stamp: the next run tries again
        calls.unlink()
    r = setup(venv)  # no stamp at all (a venv made before stamps, or a failed install): pip runs
    assert r.returncode != 0 and "-m pip install" in calls.read_text()
