"""The type stubs shipped with the package match the extension module (mypy's stubtest)."""

import subprocess
import sys

import pytest


def test_the_stubs_match_the_module():
    pytest.importorskip("mypy")
    out = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "twinstack._native", "--ignore-disjoint-bases"],
        capture_output=True, text=True, timeout=600,
    )
    assert out.returncode == 0, out.stdout + out.stderr
