"""Fixtures the test files share."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def weights_tool() -> Path:
    override = os.environ.get("SCDP_WEIGHTS_TOOL")
    if override:
        return Path(override)
    target = Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target"))
    binary = target / "release" / "weights-tool"
    if shutil.which("cargo"):
        # A no-op when the binary is current; a stale one could write another format version.
        subprocess.run(
            ["cargo", "build", "--release", "--quiet", "-p", "weights-tool"],
            cwd=ROOT,
            check=True,
        )
    if not binary.exists():
        pytest.fail(f"{binary} does not exist and cargo is not on PATH to build it")
    return binary
