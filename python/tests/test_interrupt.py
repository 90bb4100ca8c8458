"""Ctrl-C during a stream: the stream stops at once, the board is told to stop, and the
exception is Python's KeyboardInterrupt."""

import _thread
import signal
import threading
import time

import numpy as np
import pytest


@pytest.fixture
def ctrl_c():
    """Python's own SIGINT handler, whatever this process inherited: a process started in the
    background by a shell ignores SIGINT, and `interrupt_main` then does nothing."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_stops_a_stream_and_the_board(board, ctrl_c):
    # 50 000 setpoints at 500/s: 100 s of stream (the in-process board runs its ticks faster
    # than real time, several million a second on a fast host).
    setpoints = 20.0 * np.sin(np.linspace(0.0, 40.0 * np.pi, 50_000))
    timer = threading.Timer(0.5, _thread.interrupt_main)
    timer.start()
    t0 = time.monotonic()
    try:
        with pytest.raises(KeyboardInterrupt):
            board.stream(setpoints, rate=500.0)
    finally:
        timer.cancel()
    elapsed = time.monotonic() - t0
    assert elapsed < 3.0, f"the stream ran on for {elapsed:.1f} s after Ctrl-C"
    # The line is clean and the board stopped: not streaming, the queue no longer played.
    s = board.status()
    assert "streaming" not in s["flags"], s
    fill = s["queue_fill"]
    time.sleep(0.05)
    assert board.status()["queue_fill"] == fill
    # The board takes the next stream (what was queued plays first, as after `twinstack stop`).
    report = board.stream(np.zeros(10))
    assert report["accepted"] == 10
