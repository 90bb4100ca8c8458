"""The example script runs end to end against a virtual board and writes its figure."""

import subprocess
import sys

from conftest import REPO


def test_the_workflow_example_runs(virtual_board, tmp_path):
    png = tmp_path / "workflow.png"
    out = subprocess.run(
        [sys.executable, str(REPO / "python" / "examples" / "workflow.py"),
         "--port", virtual_board, "--out", str(png)],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.count("streamed 2000 setpoints") == 2, out.stdout
    assert png.stat().st_size > 10_000
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
