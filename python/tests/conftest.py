"""Fixtures: the repository, the `twinstack` binary, a virtual board process, boards of both kinds.

The `twinstack` binary is `$TWINSTACK_HAL_SIM` when set (`cargo xtask test` builds it and sets
it), else built here with `cargo build -p twinstack-cli`.
"""

import json
import os
import pathlib
import subprocess
import sys

import pytest

import twinstack

REPO = pathlib.Path(__file__).resolve().parents[2]


def _build_hal_sim() -> str:
    out = subprocess.run(
        ["cargo", "build", "-p", "twinstack-cli", "--bin", "twinstack", "--message-format=json"],
        cwd=REPO,
        check=True,
        stdout=subprocess.PIPE,
        text=True,
    ).stdout
    for line in out.splitlines():
        msg = json.loads(line)
        if msg.get("reason") == "compiler-artifact" and msg.get("executable"):
            if msg["target"]["name"] == "twinstack":
                return msg["executable"]
    raise RuntimeError("cargo built no twinstack executable")


@pytest.fixture(scope="session")
def hal_sim() -> str:
    """Path of the `twinstack` command-line tool."""
    path = os.environ.get("TWINSTACK_HAL_SIM") or _build_hal_sim()
    assert os.access(path, os.X_OK), path
    return path


def _serve_virtual_board(hal_sim, *options):
    """Starts `twinstack virtual-board` on a free TCP port: the process and its port."""
    proc = subprocess.Popen(
        [hal_sim, "virtual-board", "--listen", "tcp:127.0.0.1:0", *options],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = proc.stdout.readline()
    # "virtual board listening on tcp:127.0.0.1:PORT (...)"
    words = line.split()
    if proc.poll() is not None or "listening" not in words:
        proc.kill()
        raise RuntimeError(f"virtual board did not start: {line!r} {proc.stderr.read()!r}")
    return proc, words[words.index("on") + 1]


@pytest.fixture(scope="session")
def virtual_board(hal_sim):
    """A `twinstack virtual-board` process on a free TCP port, real-time paced: its port."""
    proc, port = _serve_virtual_board(hal_sim)
    yield port
    proc.kill()
    proc.wait()


@pytest.fixture
def dual_stage_board(hal_sim):
    """A fresh dual-stage virtual board (`--dual-stage`: the piezo stage on a ball screw, its
    coarse axis unhomed at power-up), connected."""
    proc, port = _serve_virtual_board(hal_sim, "--dual-stage")
    board = twinstack.Board(port)
    yield board
    board.close()
    proc.kill()
    proc.wait()


@pytest.fixture(params=["sim", "virtual"])
def board(request):
    """A board of each kind: in-process (`"sim"`) and a virtual board process over TCP. The
    virtual board keeps its state between tests: each test starts it in bypass with the
    paper's settings recalled from its flash."""
    if request.param == "sim":
        b = twinstack.Board("sim")
    else:
        b = twinstack.Board(request.getfixturevalue("virtual_board"))
        b.stop()
        b.recall()
        b.mode("bypass")
    yield b
    b.close()


def param_json(settings: dict, output_sign: float = 1.0) -> str:
    """A parameter file's JSON around `settings` (a board's, from `Board.params()`)."""
    return json.dumps(
        {
            "format": "twinstack-params",
            "version": 2,
            "units": {"time": "s", "input": "V", "output": "um"},
            "output_sign": output_sign,
            "sensor_lag_s": 0.0,
            "settings": settings,
        }
    )


@pytest.fixture
def python_exe() -> str:
    return sys.executable
