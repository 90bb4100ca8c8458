"""The dual-actuated stage's coarse axis from Python, on a dual-stage virtual board."""

import pytest

import twinstack
from twinstack.bluesky import CoarseAxis


def test_the_coarse_axis_homes_moves_and_reports_and_refuses_what_it_cannot_do(dual_stage_board):
    board = dual_stage_board
    s = board.coarse_status()
    assert s["state"] == "unhomed" and not s["homed"]
    # Not homed: a move is refused by the board, naming why.
    with pytest.raises(twinstack.BoardError):
        board.coarse_move(5.0)
    homed = board.coarse_home()
    assert homed["homed"] and homed["state"] == "idle" and homed["faults"] == []
    moved = board.coarse_move(5.0, speed=10.0, accel=200.0)
    assert moved["state"] == "idle" and moved["position_mm"] == pytest.approx(5.0, abs=0.002)
    assert moved["setpoint_mm"] == pytest.approx(5.0, abs=1e-6)
    # Beyond the stage's speed: refused with the limit, nothing moves.
    with pytest.raises(twinstack.BoardError) as e:
        board.coarse_move(0.0, speed=1000.0)
    assert e.value.limit is not None
    assert board.coarse_status()["position_mm"] == pytest.approx(5.0, abs=0.002)
    # A jog runs until stopped; the stop brakes, still homed.
    board.coarse_jog(2.0)
    assert board.coarse_status()["state"] == "jogging"
    board.coarse_stop()
    stopped = board.coarse_move(0.0)
    assert stopped["homed"] and stopped["position_mm"] == pytest.approx(0.0, abs=0.002)
    with pytest.raises(ValueError, match="timeout"):
        board.coarse_home(timeout=0.0)


def test_the_piezo_handed_back_scans_on_its_own_and_the_next_move_takes_it_back(dual_stage_board):
    board = dual_stage_board
    board.coarse_home()
    assert board.coarse_status()["piezo"] == "coarse"
    # Owned by the coarse axis, the piezo's own sources are refused.
    with pytest.raises(twinstack.BoardError):
        board.waveform(amplitude=0.2, frequency=20.0)
    board.coarse_release()
    held = board.coarse_status()
    assert held["piezo"] == "own"
    board.waveform(amplitude=0.2, frequency=20.0)
    # A move while the piezo's waveform plays would cut it off: refused.
    with pytest.raises(twinstack.BoardError):
        board.coarse_move(1.0)
    board.stop()
    # The carriage held: the axis's position (the linear scale: carriage and piezo) moved by
    # no more than the piezo's waveform, 0.2 of its ±40 µm; its setpoint not at all.
    after = board.coarse_status()
    assert after["state"] == "idle" and after["setpoint_mm"] == held["setpoint_mm"]
    assert after["position_mm"] == pytest.approx(held["position_mm"], abs=0.010)
    moved = board.coarse_move(1.0)
    assert moved["state"] == "idle" and moved["position_mm"] == pytest.approx(1.0, abs=0.002)
    assert board.coarse_status()["piezo"] == "coarse"


def test_a_board_without_a_coarse_axis_says_so():
    with twinstack.Board("sim") as board, pytest.raises(twinstack.BoardError):
        board.coarse_status()


def test_a_bluesky_step_scan_of_the_coarse_axis(dual_stage_board):
    pytest.importorskip("bluesky")
    from bluesky import RunEngine
    from bluesky import plans as bp
    from bluesky.protocols import Movable, Readable, check_supports

    board = dual_stage_board
    board.coarse_home()
    coarse = CoarseAxis(board, name="coarse", speed=10.0)
    check_supports(coarse, Movable)
    check_supports(coarse, Readable)
    engine = RunEngine({})
    docs = []
    engine.subscribe(lambda name, doc: docs.append((name, doc)))
    try:
        engine(bp.scan([], coarse, -1.0, 1.0, 3))
    finally:
        engine.loop.call_soon_threadsafe(engine.loop.stop)
    events = [d for n, d in docs if n == "event"]
    assert [e["data"]["coarse_setpoint"] for e in events] == pytest.approx([-1.0, 0.0, 1.0])
    assert [e["data"]["coarse"] for e in events] == pytest.approx([-1.0, 0.0, 1.0], abs=0.002)
    # A move the board refuses fails its status with the refusal.
    with pytest.raises(twinstack.BoardError):
        coarse.set(1000.0).wait(10.0)
