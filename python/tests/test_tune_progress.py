"""`Board.tune(progress=...)`: each measured point handed to the caller as it comes, an
exception from the caller or Ctrl-C stopping the sweep with the board as it was (generator
stopped, mode restored, nothing loaded)."""

import _thread
import asyncio
import signal
import threading
import time

import pytest

import twinstack


class Enough(Exception):
    """The caller's own reason to stop."""


def _as_before(board, mode, feedback):
    s = board.status()
    assert s["mode"] == mode, s
    assert "waveform" not in s["flags"], s
    assert board.params()["feedback"] == feedback, "nothing was loaded"


def test_progress_sees_every_point_the_report_has(board):
    seen = []
    r = board.tune(progress=seen.append)
    assert len(seen) == len(r["points"]) > 20
    # The same points: the report's in order of frequency, the progress's as measured.
    key = lambda p: p["frequency_hz"]
    for p, q in zip(sorted(seen, key=key), r["points"]):
        assert {k: p[k] for k in q} == q
        assert p["drive_volts"] > 0.0 and p["sensor_amplitude"] > 0.0, p


def test_an_exception_from_progress_stops_the_sweep_and_goes_up(board):
    board.mode("closed-loop")
    before = board.params()["feedback"]
    seen = []

    def progress(point):
        seen.append(point)
        if len(seen) == 2:
            raise Enough(point["frequency_hz"])

    with pytest.raises(Enough):
        board.tune(load=True, progress=progress)
    assert len(seen) == 2, "no point measured after the stop"
    _as_before(board, "closed-loop", before)
    # The board takes the next tune.
    r = board.tune()
    assert r["loaded"] is False and len(r["points"]) > 20


def test_progress_that_is_not_callable_is_refused_before_anything_moves():
    with twinstack.Board("sim") as board:
        ticks = board.status()["ticks"]
        with pytest.raises(TypeError, match="progress"):
            board.tune(progress=3)
        assert board.status()["ticks"] - ticks < 200


@pytest.fixture
def ctrl_c():
    """Python's own SIGINT handler, whatever this process inherited (a process started in the
    background by a shell ignores SIGINT)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_stops_the_sweep_and_restores_the_board(virtual_board, ctrl_c):
    # The virtual board runs in real time: its sweep lasts well over the 0.3 s before Ctrl-C.
    with twinstack.Board(virtual_board) as board:
        board.stop()
        board.recall()
        board.mode("closed-loop")
        before = board.params()["feedback"]
        seen = []
        timer = threading.Timer(0.3, _thread.interrupt_main)
        timer.start()
        t0 = time.monotonic()
        try:
            with pytest.raises(KeyboardInterrupt):
                board.tune(load=True, progress=seen.append)
        finally:
            timer.cancel()
        elapsed = time.monotonic() - t0
        assert elapsed < 1.5, f"the sweep ran on for {elapsed:.1f} s after Ctrl-C"
        _as_before(board, "closed-loop", before)
        board.mode("bypass")


def test_the_async_board_passes_progress_on():
    async def main():
        async with await twinstack.AsyncBoard.open("sim") as board:
            seen = []
            r = await board.tune(progress=seen.append)
            assert len(seen) == len(r["points"]) > 20

            def stop(point):
                raise Enough(point["frequency_hz"])

            with pytest.raises(Enough):
                await board.tune(load=True, progress=stop)
            assert (await board.status())["mode"] == "bypass"

    asyncio.run(main())
