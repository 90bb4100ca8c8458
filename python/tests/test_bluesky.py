"""The bluesky devices under bluesky's own RunEngine, against the in-process board: a step scan
of 21 points with every event's position within the settle window, and a fly scan of a
32-line raster, every pixel's position within the window of its setpoint."""

import numpy as np
import pytest

import twinstack
from twinstack.bluesky import Axis, Flyer, ScanFlyer, SettleTimeout, Status

bluesky = pytest.importorskip("bluesky")
from bluesky import RunEngine  # noqa: E402
from bluesky import plans as bp  # noqa: E402
from bluesky.protocols import Flyable, Movable, Readable, check_supports  # noqa: E402

WINDOW = 0.2  # µm: the settle window of the tests (0.2 % of the simulated stage's 90 µm span)


@pytest.fixture(scope="module")
def stage_params():
    """The simulated stage's model, calibrated once (`Board.calibrate`): every in-process board
    runs the same stage, so it serves them all."""
    with twinstack.Board("sim") as b:
        return b.calibrate(store=False)["params"]


@pytest.fixture
def board(stage_params):
    """A simulated board with its stage calibrated, in closed loop: the lab's workflow."""
    b = twinstack.Board("sim")
    b.load(stage_params, mode="closed-loop")
    yield b
    b.close()


@pytest.fixture
def RE():
    engine = RunEngine({})
    docs = []
    engine.subscribe(lambda name, doc: docs.append((name, doc)))
    engine.docs = docs
    yield engine
    # RunEngine runs its loop in a thread of its own: stop it.
    engine.loop.call_soon_threadsafe(engine.loop.stop)


def events(docs, stream):
    """The events of `stream`, event pages (what `collect` gives) unpacked."""
    from event_model import unpack_event_page

    descriptors = {d["uid"] for n, d in docs if n == "descriptor" and d["name"] == stream}
    out = []
    for n, d in docs:
        if n == "event" and d["descriptor"] in descriptors:
            out.append(d)
        elif n == "event_page" and d["descriptor"] in descriptors:
            out.extend(unpack_event_page(d))
    return out


def test_the_axis_follows_bluesky_protocols(board):
    x = Axis(board, name="x", window=WINDOW)
    check_supports(x, Movable)
    check_supports(x, Readable)
    assert x.hints == {"fields": ["x"]}
    assert set(x.describe()) == {"x", "x_setpoint", "x_error"}
    assert set(x.read_configuration()) == set(x.describe_configuration())
    assert x.parent is None
    with pytest.raises(ValueError, match="outside the output range"):
        x.set(1e6)


def test_a_step_scan_of_21_points_settles_at_every_point(board, RE):
    x = Axis(board, name="x", window=WINDOW)
    uids = RE(bp.scan([x], x, -20.0, 20.0, 21))
    assert len(uids) == 1
    evs = events(RE.docs, "primary")
    assert len(evs) == 21
    targets = np.linspace(-20.0, 20.0, 21)
    for ev, target in zip(evs, targets):
        assert abs(ev["data"]["x"] - target) <= WINDOW, (target, ev["data"])
        assert abs(ev["data"]["x_setpoint"] - target) <= 1e-2, (target, ev["data"])
        assert ev["timestamps"]["x"] > 0
    stop = [d for n, d in RE.docs if n == "stop"][0]
    assert stop["exit_status"] == "success"


def test_a_move_that_cannot_settle_fails_its_status(board):
    board.mode("bypass")  # no feedback: hysteresis leaves the sensor off the target
    x = Axis(board, name="x", window=1e-3, timeout=0.2)
    st = x.set(10.0)
    with pytest.raises(SettleTimeout, match="not settled at 10.0"):
        st.wait(30.0)
    assert st.done and not st.success
    seen = []
    st.add_callback(seen.append)
    assert seen == [st], "a callback added after the end runs at once"


def test_a_fly_scan_of_a_32_line_raster(board, RE):
    fly = Flyer.raster(board, lines=32, pixels=32, amplitude=0.3, per_pixel=20, rate=5000.0)
    check_supports(fly, Flyable)
    RE(bp.fly([fly]))
    evs = events(RE.docs, "raster")
    assert len(evs) == 32 * 32
    lines = [e["data"]["raster_line"] for e in evs]
    assert lines == [k for k in range(32) for _ in range(32)]
    pixels = [e["data"]["raster_pixel"] for e in evs]
    assert pixels[:32] == list(range(32)) and pixels[32:64] == list(range(31, -1, -1))
    err = [abs(e["data"]["raster"] - e["data"]["raster_setpoint"]) for e in evs]
    assert max(err) <= WINDOW, max(err)
    times = [e["timestamps"]["raster"] for e in evs]
    assert times == sorted(times)
    # One event every 20 setpoints at 5 kHz: timestamps 4 ms apart on the board's clock.
    assert np.allclose(np.diff(times), 0.004, atol=1e-6)
    assert fly.report["accepted"] == 32 * 32 * 20 and not fly.report["underran"]


def test_a_fly_scan_of_the_board_s_own_raster_gives_one_event_per_pixel_clock(board, RE):
    fly = ScanFlyer(board, "raster:lines=6,pixels=50,turn=40,amplitude=0.6", ticks_per_pixel=4)
    check_supports(fly, Flyable)
    RE(bp.fly([fly]))
    evs = events(RE.docs, "scan")
    assert len(evs) == 6 * 50
    assert [e["data"]["scan_frame"] for e in evs] == [0] * 300
    assert [e["data"]["scan_line"] for e in evs] == [k for k in range(6) for _ in range(50)]
    pixels = [e["data"]["scan_pixel"] for e in evs]
    assert pixels[:50] == list(range(50)) and pixels[50:100] == list(range(49, -1, -1))
    # A pixel's position is its place along the line, whichever way the line runs.
    x = np.array([e["data"]["scan_setpoint"] for e in evs]).reshape(6, 50)
    by_place = np.array([row if k % 2 == 0 else row[::-1] for k, row in enumerate(x)])
    assert np.all(np.diff(by_place[0]) > 0)
    assert np.abs(by_place - by_place[0]).max() < 2.0 * 0.6 * 45 / 50
    # One pixel every 4 ticks at 50 kHz on the board's clock, within a line.
    times = np.array([e["timestamps"]["scan_setpoint"] for e in evs])
    assert np.allclose(np.diff(times.reshape(6, 50), axis=1), 8e-5, atol=1e-6)
    assert fly.figures["line"]["jitter_ticks"] == 0
    with pytest.raises(ValueError, match="frames 0"):
        ScanFlyer(board, "raster:lines=2,pixels=4", frames=0)


def test_a_fly_scan_numbers_pixels_by_the_kind_of_pattern_the_board_parsed(board, RE):
    # A raster named in capitals is still a raster: its second line's pixels are numbered
    # back along the line. A Lissajous figure's are numbered in time within each line.
    raster = ScanFlyer(board, "RASTER:lines=2,pixels=10,turn=40", name="r")
    lissajous = ScanFlyer(board, "lissajous:hz=500,x=3,y=2", name="l")
    RE(bp.fly([raster]))
    RE(bp.fly([lissajous]))
    pixels = [e["data"]["r_pixel"] for e in events(RE.docs, "r")]
    assert pixels == list(range(10)) + list(range(9, -1, -1))
    by_line: dict = {}
    for e in events(RE.docs, "l"):
        by_line.setdefault((e["data"]["l_frame"], e["data"]["l_line"]), []).append(e["data"]["l_pixel"])
    assert by_line and all(p == list(range(len(p))) for p in by_line.values()), by_line


def test_a_fly_scan_shaped_for_the_resonance_calibrate_measured(board, stage_params, RE):
    # One setpoint a tick: the shaping needs the next setpoints where the board holds each.
    tick = float(board.status()["tick_rate_hz"])
    resonance = stage_params.resonance
    assert resonance is not None, "calibrate measured the stage's resonance"
    with pytest.raises(ValueError, match="one setpoint a tick"):
        Flyer.raster(board, lines=4, pixels=32, rate=tick / 10, resonance=resonance)
    fly = Flyer.raster(
        board, lines=8, pixels=32, amplitude=0.3, per_pixel=20, rate=tick, resonance=resonance
    )
    RE(bp.fly([fly]))
    evs = events(RE.docs, "raster")
    assert len(evs) == 8 * 32
    assert fly.report["accepted"] == 8 * 32 * 20 and not fly.report["underran"]
    # The board played the shaped trajectory, and the stage followed it to the pixel.
    err = [abs(e["data"]["raster"] - e["data"]["raster_setpoint"]) for e in evs]
    assert max(err) <= WINDOW, max(err)
    # The flyer streams with the resonance: in bypass the board's shaping refuses it.
    board.mode("bypass")
    bypassed = Flyer.raster(board, lines=2, pixels=8, rate=tick, resonance=resonance)
    bypassed.kickoff()
    with pytest.raises(ValueError, match="the board is in Bypass"):
        bypassed.complete().wait(30.0)


def test_status_callbacks_and_failure():
    s = Status("x")
    seen = []
    s.add_callback(seen.append)
    assert not s.done
    s._finish(RuntimeError("boom"))
    assert seen == [s] and s.done and not s.success
    assert isinstance(s.exception(), RuntimeError)
