"""The asyncio API: a stream and a status poll run concurrently in one event loop, against the
in-process board and a virtual board process; calls on one board queue instead of failing;
a cancelled stream stops the board and leaves its line clean."""

import asyncio
import time

import numpy as np
import pytest

import twinstack
from twinstack.aio import AsyncBoard


@pytest.fixture(params=["sim", "virtual"])
def port(request):
    if request.param == "sim":
        return "sim"
    port = request.getfixturevalue("virtual_board")
    with twinstack.Board(port) as b:
        b.stop()
        b.recall()
        b.mode("bypass")
    return port


def test_a_stream_and_a_status_poll_run_concurrently(port):
    async def main():
        async with await AsyncBoard.open(port) as board:
            # 3 s of setpoints at 5 kHz, in chunks of 0.5 s.
            setpoints = 10.0 * np.sin(np.linspace(0.0, 30 * np.pi, 15000))
            polls = []
            ticks_of_polls = []
            done = asyncio.Event()

            async def poll():
                while not done.is_set():
                    s = await board.status()
                    polls.append("streaming" in s["flags"])
                    ticks_of_polls.append(s["ticks"])
                    await asyncio.sleep(0)

            async def run_stream():
                try:
                    return await board.stream(setpoints, rate=5000.0)
                finally:
                    done.set()

            # A heartbeat proves the loop itself is never blocked by the stream: it yields
            # after each beat, and records whether the stream was still running.
            beats = []

            async def heartbeat():
                while not done.is_set():
                    beats.append(len(polls))
                    await asyncio.sleep(0)

            report, _, _ = await asyncio.gather(run_stream(), poll(), heartbeat())
            return report, polls, ticks_of_polls, beats

    report, polls, ticks, beats = asyncio.run(main())
    assert report["accepted"] == 15000
    assert report["chunks"] == 6
    assert report["drained"]
    assert not report["underran"], report
    # Polls answered while the stream was playing, with the board's time running between them.
    assert sum(polls) >= 3, polls
    assert ticks == sorted(ticks) and ticks[-1] > ticks[0]
    # The loop ran throughout: beats came between polls while the stream was playing, not
    # only before it started or after it ended (ordering, not wall-clock time).
    assert len(set(beats)) >= 3, beats[:20]


def test_calls_on_one_board_queue_instead_of_failing():
    async def main():
        async with await AsyncBoard.open("sim") as board:
            results = await asyncio.gather(*[board.status() for _ in range(8)])
            modes = await asyncio.gather(board.mode("open-loop"), board.status())
            return results, modes[1]

    results, after = asyncio.run(main())
    assert [r["image"] for r in results] == ["simulator"] * 8
    ticks = [r["ticks"] for r in results]
    assert ticks == sorted(ticks), "served in the order asked"
    assert after["mode"] == "open-loop"


def test_cancelling_a_stream_stops_the_board_and_leaves_the_line_clean():
    async def main():
        async with await AsyncBoard.open("sim") as board:
            # 100 s of stream at 500/s.
            setpoints = 20.0 * np.sin(np.linspace(0.0, 40.0 * np.pi, 50_000))
            task = asyncio.create_task(board.stream(setpoints, rate=500.0))
            await asyncio.sleep(0.3)
            t0 = time.monotonic()
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            elapsed = time.monotonic() - t0
            s = await board.status()
            report = await board.stream(np.zeros(10))
            return elapsed, s, report

    elapsed, s, report = asyncio.run(main())
    assert elapsed < 30.0, f"the stream ran on for {elapsed:.1f} s after the cancel"
    assert "streaming" not in s["flags"], s
    assert report["accepted"] == 10


def test_numpy_in_and_out_and_errors_as_the_blocking_api():
    async def main():
        async with await AsyncBoard.open("sim") as board:
            rec = await board.record(["setpoint", "sensor"], samples=100)
            with pytest.raises(ValueError, match="expected \"bypass\""):
                await board.mode("feedback")
            with pytest.raises(twinstack.BoardError) as e:
                await board.record(["sensor"], samples=10**7)
            with pytest.raises(ValueError, match="one-dimensional"):
                await board.stream(np.zeros((2, 2)))
            return rec, e.value

    rec, err = asyncio.run(main())
    assert set(rec) == {"t", "setpoint", "sensor"}
    assert rec["sensor"].dtype == np.float64 and rec["sensor"].shape == (100,)
    assert err.field == "record count"


def test_tune_is_awaited_as_the_blocking_call():
    async def main():
        async with await AsyncBoard.open("sim") as board:
            checked = await board.tune(kp=0.2, ki=3000.0)
            with pytest.raises(ValueError, match="kp and ki"):
                await board.tune(ki=3000.0)
            return checked

    checked = asyncio.run(main())
    assert checked["feedback"]["kp"] == 0.2 and checked["figures"]["stable"]
    assert checked["fit"]["resonance_hz"] == pytest.approx(21_800.0, rel=0.01)


def test_identify_runs_in_a_worker_thread(monkeypatch):
    import pathlib
    import threading

    data = pathlib.Path(__file__).resolve().parents[2] / "data" / "micromanipulator-unipolar-3v6-1hz.csv"
    t, u, x = np.loadtxt(data, delimiter=",", skiprows=5).T

    # The fit waits, off the loop, for a coroutine on the loop: with the fit on the loop's own
    # thread that coroutine could never run, and the wait would give up. No clock decides it.
    real_identify = twinstack.aio._identify
    loop_ran = threading.Event()
    seen = {}

    def identify_after_the_loop_runs(*args, **kwargs):
        seen["waited"] = loop_ran.wait(timeout=60.0)
        seen["thread"] = threading.get_ident()
        return real_identify(*args, **kwargs)

    monkeypatch.setattr(twinstack.aio, "_identify", identify_after_the_loop_runs)

    async def main():
        fit = asyncio.ensure_future(twinstack.aio.identify(t, u, x, model="pi", fit_until=16.0))
        # The fit has started (the loop ran its task); the loop runs on.
        await asyncio.sleep(0)
        loop_ran.set()
        return await fit

    params = asyncio.run(main())
    assert params.model == "pi"
    assert seen["waited"], "the event loop did not run while the model was fitted"
    assert seen["thread"] != threading.get_ident(), "the fit ran on the event loop's thread"


def test_a_stream_shaped_for_the_resonance_is_shaped_whole_then_sent_in_chunks():
    async def main():
        async with await AsyncBoard.open("sim") as board:
            await board.mode("open-loop")
            tick = float((await board.status())["tick_rate_hz"])
            ranges = (await board.params())["ranges"]
            # A 250 Hz triangle of ±20 µm, one setpoint a tick, in chunks of 300 setpoints: the
            # corners fall inside chunks and at their edges.
            phase = np.mod(np.arange(2000) / (tick / 250.0), 1.0)
            setpoints = 40.0 * np.where(phase < 0.5, phase, 1.0 - phase) - 10.0
            resonance = (21800.0, 0.017)
            whole = await board.shaped(setpoints, resonance)
            await board.arm(["setpoint"], samples=2000, trigger="stream")
            report = await board.stream(setpoints, resonance=resonance, chunk=300)
            played = (await board.fetch(timeout=10))["setpoint"]
            await board.mode("bypass")
            return setpoints, ranges, whole, report, played

    setpoints, ranges, whole, report, played = asyncio.run(main())
    assert report["accepted"] == 2000 and report["chunks"] == 7
    lo, hi = float(ranges["output_min"]), float(ranges["output_max"])
    lsb = (hi - lo) / 65536
    # The board played the trajectory shaped as a whole (no chunk's edge shaped as an end),
    # as one stream: every recorded setpoint is the whole's, with no pause between chunks.
    expected = (lo + hi) / 2 + (hi - lo) / 2 * whole
    assert np.max(np.abs(played - expected)) <= 2 * lsb
    assert report["underruns"] == 0 and not report["underran"]
    # ...which is not the trajectory as it came: its corners were shaped.
    assert np.max(np.abs(expected - setpoints)) > 50 * lsb


def test_a_bad_setpoint_in_a_later_chunk_is_refused_before_anything_is_sent():
    # The whole trajectory is checked first: the error names the setpoint's index in it,
    # and the board has not moved (no chunk sent, nothing queued, no stream running).
    async def main():
        async with await AsyncBoard.open("sim") as board:
            before = await board.status()
            setpoints = np.r_[np.linspace(0.0, 0.5, 3000), np.nan]
            with pytest.raises(ValueError, match=r"setpoints\[3000\]"):
                await board.stream(setpoints, normalised=True, chunk=1000)
            return before, await board.status()

    before, after = asyncio.run(main())
    assert "streaming" not in after["flags"]
    assert after["queue_fill"] == 0
    assert after["next_seq"] == before["next_seq"]


def test_a_closed_board_says_so_and_closes_again_quietly():
    async def main():
        board = await AsyncBoard.open("sim")
        await board.close()
        await board.close()
        with pytest.raises(RuntimeError, match="the board is closed"):
            await board.status()

    asyncio.run(main())
