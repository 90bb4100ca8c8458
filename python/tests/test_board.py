"""Every Board method against the in-process board and a virtual board process."""

import json
import subprocess
import threading
import time
import warnings

import numpy as np
import pytest

import twinstack
from conftest import param_json


def test_status_reports_the_simulated_board(board):
    s = board.status()
    assert s["image"] == "simulator"
    assert s["tick_rate_hz"] == 50000
    assert s["mode"] == "bypass"
    assert s["queue_fill"] == 0 and s["credits"] > 0
    assert s["drifts"] == 0, "the defaults have no observer, so no drift check"
    ticks = s["ticks"]
    assert board.status()["ticks"] > ticks, "the board's time runs"


def test_mode_switches_and_a_bad_name_is_refused_before_sending(board):
    board.mode("open-loop")
    assert board.status()["mode"] == "open-loop"
    board.mode("closed_loop")
    assert board.status()["mode"] == "closed-loop"
    with pytest.raises(ValueError, match="expected \"bypass\""):
        board.mode("feedback")
    assert board.status()["mode"] == "closed-loop"


def test_params_reads_back_what_load_sent(board):
    settings = board.params()
    assert settings["ranges"]["input_max"] == 140.0
    settings["drive"]["slew_rate"] = 800000.0
    settings["mode"] = "OpenLoop"
    board.load(twinstack.Params.from_json(param_json(settings)))
    back = board.params()
    assert back["drive"]["slew_rate"] == 800000.0
    assert back["mode"] == "OpenLoop"
    assert board.status()["mode"] == "open-loop"
    # `mode=` overrides the file's.
    board.load(twinstack.Params.from_json(param_json(settings)), mode="bypass")
    assert board.status()["mode"] == "bypass"


def test_load_with_preview_runs_the_file_s_resonance_and_preview_false_turns_it_off(board):
    settings = board.params()
    settings["preview"] = None
    plain = twinstack.Params.from_json(param_json(settings))
    board.load(plain)
    with pytest.raises(ValueError, match="preview=True needs the stage's resonance"):
        board.load(plain, preview=True)
    assert board.params()["preview"] is None, "nothing was loaded"
    measured = json.loads(param_json(settings))
    measured["resonance"] = {"frequency_hz": 21800.0, "damping": 0.017}
    board.load(twinstack.Params.from_json(json.dumps(measured)), preview=True)
    assert board.params()["preview"] == {"frequency_hz": 21800.0, "damping": 0.017}
    # A file without one keeps the board's; preview=False takes it away.
    board.load(plain)
    assert board.params()["preview"] == {"frequency_hz": 21800.0, "damping": 0.017}
    board.load(plain, preview=False)
    assert board.params()["preview"] is None


def test_a_load_the_board_refuses_raises_board_error_with_field_and_limit(board):
    settings = board.params()
    # Two ticks at 100 kHz, less than two at the board's 50 kHz: the file is valid (a board
    # at 100 kHz takes it), this board refuses it.
    settings["creep"] = {"time_constants_s": [3e-5], "weights": [0.01]}
    params = twinstack.Params.from_json(param_json(settings))
    before = board.params()
    with pytest.raises(twinstack.BoardError) as e:
        board.load(params)
    err = e.value
    assert err.request == "LoadParams"
    assert err.field == "creep.time_constants_s[0]"
    assert err.rule == "AtLeast"
    assert err.limit == pytest.approx(4e-5)
    assert "must be at least" in err.reason
    assert board.params() == before, "nothing was applied"


def test_a_model_the_drive_cannot_reach_is_refused_unless_clamp(board):
    settings = board.params()
    settings["ranges"]["input_min"] = -150.0
    settings["ranges"]["input_max"] = 150.0
    wide = twinstack.Params.from_json(param_json(settings))
    with pytest.raises(twinstack.BoardError) as e:
        board.load(wide)
    assert e.value.field == "ranges.input"
    assert "-150…150 V" in str(e.value) and "clamp=True" in str(e.value)
    assert board.params()["ranges"]["input_min"] == 0.0
    with pytest.warns(RuntimeWarning, match="clamp=True"):
        board.load(wide, clamp=True)
    assert board.params()["ranges"]["input_min"] == -150.0


def test_closed_loop_on_an_inverted_sensor_is_refused(board):
    settings = board.params()
    settings["mode"] = "ClosedLoop"
    inverted = twinstack.Params.from_json(param_json(settings, output_sign=-1.0))
    with pytest.raises(twinstack.BoardError) as e:
        board.load(inverted)
    assert e.value.field == "output_sign"
    assert board.status()["mode"] == "bypass"


def test_store_and_recall(board):
    settings = board.params()
    settings["drive"]["slew_rate"] = 700000.0
    board.load(twinstack.Params.from_json(param_json(settings)), store="open-loop")
    settings["drive"]["slew_rate"] = 600000.0
    board.load(twinstack.Params.from_json(param_json(settings)))
    assert board.params()["drive"]["slew_rate"] == 600000.0
    board.recall()
    assert board.params()["drive"]["slew_rate"] == 700000.0
    assert board.params()["mode"] == "OpenLoop"
    board.load(twinstack.Params.from_json(param_json(settings)))
    board.store()  # bypass
    board.recall()
    assert board.params()["mode"] == "Bypass"


def test_a_streamed_run_is_recorded_with_four_signals_in_physical_units(board):
    # 100 setpoints in µm (the paper settings' output range is ±45 µm), one every 5 ticks.
    n, divider = 100, 5
    setpoints = 20.0 * np.sin(np.linspace(0.0, 2.0 * np.pi, n))
    frames = n * divider
    board.arm(["setpoint", "left", "sensor", "estimate"], samples=frames, trigger="stream")
    report = board.stream(setpoints, rate=50000 / divider)
    assert report["accepted"] == n and report["divider"] == divider
    assert report["underruns"] == 0 and not report["underran"]
    run = board.fetch(timeout=10)
    assert sorted(run) == ["estimate", "left", "sensor", "setpoint", "t"]
    for name, values in run.items():
        assert values.dtype == np.float64 and values.shape == (frames,), name
    assert run["t"][0] == 0.0 and run["t"][1] == pytest.approx(2e-5)
    # The board moves from one setpoint to the next over `divider` ticks (linear
    # interpolation) and reaches setpoint k at frame k × divider + divider − 1: there it
    # is what was sent, within one Q1.15 step of the ±45 µm range (rounding both ways).
    lsb = 90.0 / 65536
    reached = run["setpoint"][divider - 1 :: divider]
    assert reached.shape == (n,)
    assert np.max(np.abs(reached - setpoints)) <= lsb
    # Bypass: the drive follows the setpoint (volts around the 70 V bias) and the stage moves.
    assert 0.0 < run["left"].min() < 70.0 < run["left"].max() < 140.0
    assert np.ptp(run["sensor"]) > 10.0


def test_a_stream_out_of_range_or_at_an_odd_rate_is_refused_before_sending(board):
    with pytest.raises(ValueError, match=r"setpoints\[2\]: x = 50 is outside"):
        board.stream(np.array([0.0, 1.0, 50.0]))
    with pytest.raises(ValueError, match="whole number"):
        board.stream(np.zeros(10), rate=30000.0)
    with pytest.raises(ValueError, match="outside -1…1"):
        board.stream(np.array([0.5, 1.5]), normalised=True)
    assert board.status()["queue_fill"] == 0, "nothing was sent"


def test_a_stream_shaped_for_the_resonance_plays_in_open_and_closed_loop_and_is_refused_in_bypass(board):
    # A 250 Hz triangle of ±20 µm, one setpoint a tick at 50 kHz; the stage's 21.8 kHz
    # resonance as `tune` fits it.
    phase = np.mod(np.arange(2000) / 200.0, 1.0)
    setpoints = 40.0 * np.where(phase < 0.5, phase, 1.0 - phase) - 10.0
    resonance = (21800.0, 0.017)
    with pytest.raises(ValueError, match="the board is in Bypass"):
        board.stream(setpoints, resonance=resonance)
    board.mode("open-loop")
    with pytest.raises(ValueError, match="one setpoint every 5 ticks"):
        board.stream(setpoints, rate=10000.0, resonance=resonance)
    with pytest.raises(ValueError, match="below half the sample rate"):
        board.stream(setpoints, resonance=(30000.0, 0.017))
    assert board.status()["queue_fill"] == 0, "nothing was sent"
    board.arm(["setpoint"], samples=2000, trigger="stream")
    report = board.stream(setpoints, resonance=resonance)
    assert report["accepted"] == 2000 and not report["underran"]
    played = board.fetch(timeout=10)["setpoint"]
    # Shaped: not the file's setpoints at the corners, and the same trajectory between them.
    lsb = 90.0 / 65536
    assert np.max(np.abs(played - setpoints)) > 50 * lsb
    assert np.median(np.abs(played - setpoints)) < 0.05 * np.ptp(setpoints)
    # Closed loop the board plays them too (its feedback follows them).
    board.mode("closed-loop")
    board.arm(["setpoint"], samples=2000, trigger="stream")
    report = board.stream(setpoints, resonance=resonance)
    assert report["accepted"] == 2000 and not report["underran"]
    closed = board.fetch(timeout=10)["setpoint"]
    assert np.max(np.abs(closed - played)) <= 2 * lsb
    board.mode("bypass")


def test_a_waveform_triggers_a_capture_and_stops(board):
    board.arm("setpoint,sensor", samples=2500, trigger="waveform", pre=100)
    board.waveform(amplitude=0.5, frequency=50.0)
    assert "waveform" in board.status()["flags"]
    run = board.fetch(timeout=10)
    board.stop()
    assert "waveform" not in board.status()["flags"]
    # Up to 100 frames before the trigger: as many as the board had captured since arming.
    assert -100 * 2e-5 <= run["t"][0] < 0.0
    sp = run["setpoint"][run["t"] >= 0]
    # Half the normalised range of ±45 µm.
    assert sp.max() == pytest.approx(22.5, abs=0.1) and sp.min() == pytest.approx(-22.5, abs=0.1)
    with pytest.raises(ValueError, match="leaves the normalised range"):
        board.waveform(amplitude=0.5, frequency=10.0, offset=0.6)
    with pytest.raises(ValueError, match="expected \"sine\""):
        board.waveform(amplitude=0.5, frequency=10.0, shape="square")


def test_record_now(board):
    run = board.record(["sensor", "error"], samples=500, decimation=2)
    assert run["t"].shape == (500,)
    assert run["t"][-1] == pytest.approx(499 * 4e-5)
    with pytest.raises(ValueError, match="unknown signal"):
        board.record(["volts"], samples=10)
    with pytest.raises(ValueError, match="pre-trigger"):
        board.record(["sensor"], samples=10, pre=5)


def test_telemetry_streams_the_running_waveform_continuously_and_counts_what_is_missing(board):
    board.waveform(amplitude=0.5, frequency=50.0)
    try:
        run = board.telemetry(["setpoint", "sensor"], rate=5000.0, seconds=0.2)
    finally:
        board.stop()
    # 50 kHz / 10: one sample every 0.2 ms, each signal its column in physical units.
    assert run["rate_hz"] == pytest.approx(5000.0) and run["decimation"] == 10
    assert run["complete"] and run["missing"] == 0 and run["lost_on_board"] == 0
    assert run["samples"] >= 1000 and run["t"].shape == (run["samples"],)
    assert np.allclose(np.diff(run["t"]), 2e-4)
    # Half the normalised range of ±45 µm, four periods of it in 0.2 s.
    sp = run["setpoint"]
    assert sp.max() == pytest.approx(22.5, abs=0.1) and sp.min() == pytest.approx(-22.5, abs=0.1)
    assert run["sensor"].shape == sp.shape
    # A rate that is not the tick rate over a whole number: the nearest one.
    near = board.telemetry("sensor", rate=7000.0, seconds=0.01)
    assert near["decimation"] == 7 and near["rate_hz"] == pytest.approx(50_000.0 / 7)


def test_telemetry_the_link_cannot_carry_or_the_board_cannot_sample_is_refused(board):
    # Six signals on every tick: 300 000 values a second, six times what the link carries.
    with pytest.raises(twinstack.BoardError, match="at most") as e:
        board.telemetry(
            ["setpoint", "left", "right", "sensor", "estimate", "error"], rate=50_000.0
        )
    assert e.value.field == "telemetry decimation" and e.value.limit == 6
    with pytest.raises(ValueError, match="ticks at 50000 Hz"):
        board.telemetry("sensor", rate=60_000.0)
    with pytest.raises(ValueError, match="seconds 0"):
        board.telemetry("sensor", seconds=0.0)
    with pytest.raises(ValueError, match="unknown signal"):
        board.telemetry("volts")


def test_the_board_s_raster_runs_with_its_clocks_as_the_library_replays_it(board):
    run = board.scan("raster:lines=6,pixels=50,turn=40,amplitude=0.6,offset=0.1", ticks_per_pixel=4)
    f = run["figures"]
    assert not run["truncated"] and run["kind"] == "raster"
    # Every setpoint and trigger level as the library's replay has them, tick for tick.
    assert f["x_mismatches"] == 0 and f["trigger_mismatches"] == 0 and f["x_compared"] > 1000
    # One frame, six lines, 300 pixels: the clocks counted in the levels returned.
    rising = lambda levels: int(np.sum(levels[1:] & ~levels[:-1]) + levels[0])
    assert (rising(run["frame"]), rising(run["line"]), rising(run["pixel"])) == (1, 6, 300)
    assert f["line"]["pulses"] == 6 and f["line"]["jitter_ticks"] == 0
    assert f["line"]["width_ticks"] == [2, 2]
    # One sample a tick from the scan's start; the pixels sweep ±0.6 around 0.1 of ±45 µm (the
    # turnarounds beyond), 50 to a line: the pixel clocks' positions within a pixel of it.
    assert np.allclose(np.diff(run["t"]), 2e-5)
    pixel = np.flatnonzero(run["pixel"][1:] & ~run["pixel"][:-1]) + 1
    at_pixels = run["setpoint"][pixel]
    step = 1.2 * 45 / 50
    assert at_pixels.max() == pytest.approx(0.7 * 45, abs=step)
    assert at_pixels.min() == pytest.approx(-0.5 * 45, abs=step)
    assert "scanning" not in board.status()["flags"]


def test_a_scan_returns_the_kind_of_pattern_the_board_parsed(board):
    # The pattern's kind as parsed (its name in any case, spaces around it), not its text.
    for pattern, kind in [
        (" Raster:lines=2,pixels=10,turn=40", "raster"),
        ("LISSAJOUS:hz=500,x=3,y=2", "lissajous"),
        ("spiral:hz=2000,turns=2", "spiral"),
    ]:
        run = board.scan(pattern)
        assert run["kind"] == kind, pattern
        assert not run["truncated"] and run["figures"]["x_mismatches"] == 0, pattern


def test_a_scan_started_by_the_camera_s_frame_waits_for_its_edge():
    # A camera on the simulated board's trigger input at 200 Hz: its first frame starts the
    # scan, which then runs as the replay has it.
    with twinstack.Board("sim", sim_camera_hz=200.0) as board:
        run = board.scan("raster:lines=4,pixels=20,turn=40", start_on="rising", timeout=5.0)
        f = run["figures"]
        assert f["x_mismatches"] == 0 and f["trigger_mismatches"] == 0
        assert f["line"]["pulses"] == 4 and f["pixel"]["pulses"] == 80
    # No edge ever comes: the scan waits, and the call says so after its timeout.
    with twinstack.Board("sim") as board:
        with pytest.raises(TimeoutError):
            board.scan("raster:lines=4,pixels=20,turn=40", start_on="rising", timeout=0.5)
        with pytest.raises(ValueError, match="start_on"):
            board.scan("raster:lines=4,pixels=20", start_on="soon")


def test_a_stream_started_by_the_camera_s_frame_waits_for_its_edge():
    # The queue primed and the input armed: the camera's first frame starts the stream, which
    # plays whole.
    ramp = np.linspace(0.0, 0.4, 500)
    with twinstack.Board("sim", sim_camera_hz=200.0) as board:
        report = board.stream(ramp, normalised=True, start_on="rising", edge_timeout=5.0)
        assert report["accepted"] == 500 and report["underruns"] == 0
        assert board.status()["queue_fill"] == 0
    # No edge ever comes: the call says so after its timeout, the input disarmed and the
    # setpoints still queued.
    with twinstack.Board("sim") as board:
        with pytest.raises(TimeoutError, match="rising edge did not come"):
            board.stream(ramp, normalised=True, start_on="rising", edge_timeout=0.05)
        s = board.status()
        assert s["queue_fill"] == 500 and "streaming" not in s["flags"]
        assert "trigger-armed" not in s["flags"]
        with pytest.raises(ValueError, match="start_on"):
            board.stream(ramp, normalised=True, start_on="soon")
        with pytest.raises(ValueError, match="edge_timeout"):
            board.stream(ramp, normalised=True, start_on="rising", edge_timeout=float("nan"))


def test_a_scan_the_board_would_refuse_is_refused_before_sending(board):
    with pytest.raises(ValueError, match="lines"):
        board.scan("raster:lines=0,pixels=50")
    with pytest.raises(ValueError, match='unknown pattern "zigzag"'):
        board.scan("zigzag:lines=4")
    with pytest.raises(ValueError, match="timeout"):
        board.scan("raster:lines=4,pixels=8", timeout=-1.0)


def test_the_learning_takes_the_error_out_of_a_periodic_motion_and_its_table_plays_again(board):
    # A 750 Hz sine in open loop: 3 cycles in a 200-tick period at 50 kHz. The learning is
    # configured first: the waveform's start restarts its period, so the table is aligned
    # with the motion's start, and plays again on the same motion started again.
    board.mode("open-loop")
    try:
        board.learn(200)
        board.waveform(amplitude=0.5, frequency=750.0)
        board.record("sensor", samples=20_000)  # 100 periods
        learned = board.learn_status()
        assert learned["state"] == "learning" and learned["period_ticks"] == 200
        assert learned["periods"] >= 100 and learned["missed"] == 0
        table = board.learn_table()
        assert table.shape == (200,) and np.abs(table).max() > 0.0
        board.stop()
        # The same motion started again: the feedforward alone (the table emptied, frozen),
        # then the kept table loaded while it runs.
        board.learn(200, reset=True)
        board.learn_state("frozen")
        board.waveform(amplitude=0.5, frequency=750.0)
        board.record("sensor", samples=2000)
        empty = board.learn_status()
        board.learn_load_table(table)
        board.record("sensor", samples=2000)
        loaded = board.learn_status()
        assert np.array_equal(board.learn_table(), table)
    finally:
        board.learn_state("off")
        board.stop()
    assert empty["state"] == loaded["state"] == "frozen"
    assert learned["error_rms"] < empty["error_rms"] / 3
    assert loaded["error_rms"] == pytest.approx(learned["error_rms"], rel=0.5)


def test_learning_settings_and_tables_are_refused_before_sending(board):
    with pytest.raises(ValueError, match="learning.period"):
        board.learn(1)
    with pytest.raises(ValueError, match="learning.cutoff_hz must be below 25000"):
        board.learn(200, cutoff_hz=30_000.0)
    with pytest.raises(ValueError, match="expected \"learning\""):
        board.learn_state("maybe")
    board.learn(200)
    board.learn_state("off")
    with pytest.raises(ValueError, match="a table of 3 values for a period of 200 ticks"):
        board.learn_load_table([0.0, 0.1, 0.2])
    with pytest.raises(ValueError, match="table\\[3\\]"):
        board.learn_load_table([0.0, 0.0, 0.0, float("nan")] + [0.0] * 196)


def test_a_capture_beyond_the_buffer_is_refused_with_its_limit(board):
    with pytest.raises(twinstack.BoardError) as e:
        board.record(
            ["setpoint", "left", "right", "sensor", "estimate", "error"], samples=1_000_000
        )
    assert e.value.field == "record count"
    assert e.value.rule in ("AtMost", "TooMany")
    # The board's buffer over six signals: 31 744 slots / 6 = 5 290 samples.
    assert e.value.limit == 31_744 // 6


def test_waiting_calls_release_the_interpreter_lock(virtual_board):
    # 25 000 frames at 50 kHz: half a second of the real-time board, waited for in Rust.
    with twinstack.Board(virtual_board) as b:
        b.recall()
        count = 0
        done = threading.Event()

        def spin():
            nonlocal count
            while not done.is_set():
                count += 1

        spinner = threading.Thread(target=spin)
        spinner.start()
        t0 = time.monotonic()
        b.record(["sensor"], samples=25_000)
        waited = time.monotonic() - t0
        seen = count
        done.set()
        spinner.join()
    assert waited >= 0.4
    # A thread that could not run while the capture was waited for would not have counted.
    assert seen > 10_000, seen


def test_a_closed_board_and_bad_ports_raise_python_errors():
    b = twinstack.Board("sim")
    b.close()
    with pytest.raises(RuntimeError, match="closed"):
        b.status()
    with pytest.raises(ValueError):
        twinstack.Board("")
    with pytest.raises(ConnectionError):
        twinstack.Board("tcp:127.0.0.1:1")
    with pytest.raises(FileNotFoundError, match="available serial ports|no serial ports"):
        twinstack.Board("/dev/does-not-exist-twinstack")
    with pytest.raises(ValueError, match="timeout"):
        twinstack.Board("sim", timeout=0)


def test_calibrate_identifies_loads_and_verifies_the_stage(board):
    """One call: excite, record, identify, load, verify (not stored, so the virtual board's
    flash keeps the paper's settings for the other tests). The simulated stage tracks within
    1 % of the trajectory's span after, several times better than before."""
    report = board.calibrate(store=False)
    assert isinstance(report["params"], twinstack.Params)
    assert report["stored"] is False
    before, after = report["before"]["max_pct"], report["after"]["max_pct"]
    assert after < 1.0, report
    assert before > 3.0 * after, report
    assert board.params()["mode"] == "open-loop" or board.status()["mode"] == "open-loop"
    # The stage's resonance measured after the excitation, as `tune` measures it (the
    # simulated stage's: 21.8 kHz, damping 0.017), and in the parameters for a preview.
    hz, damping = report["resonance"]
    assert hz == pytest.approx(21_800.0, rel=0.01) and damping == pytest.approx(0.017, rel=0.15)
    assert report["params"].resonance == report["resonance"]
    assert report["resonance_not_fitted"] is None


def test_calibrate_refuses_an_unknown_model_before_touching_the_board(board):
    with pytest.raises(ValueError, match="unknown model"):
        board.calibrate(model="preisach")


def test_calibrate_refuses_a_fastest_motion_it_cannot_sweep_or_record_naming_it(board):
    """Not above the excitation's 10 Hz, or faster than the board records with 20 samples
    a cycle: refused, naming ``fastest_hz``, with nothing streamed."""
    before = board.status()["next_seq"]
    with pytest.raises(RuntimeError, match="fastest_hz = 5"):
        board.calibrate(store=False, fastest_hz=5.0)
    with pytest.raises(RuntimeError, match="fastest_hz = 5000"):
        board.calibrate(store=False, fastest_hz=5000.0)
    assert board.status()["next_seq"] == before


def _cli_tune(hal_sim, *args):
    """`twinstack tune --port sim --json` with `args`: its one JSON object."""
    out = subprocess.run(
        [hal_sim, "tune", "--port", "sim", "--json", *args],
        check=True,
        stdout=subprocess.PIPE,
        text=True,
    ).stdout
    return json.loads(out)


def test_tune_designs_gains_for_the_margins_asked_on_the_fitted_stage(board, hal_sim):
    before = board.params()["feedback"]
    r = board.tune(phase_margin=50.0, gain_margin=8.0)
    assert r["goals"]["phase_margin_deg"] == 50.0 and r["goals"]["gain_margin_db"] == 8.0
    f = r["figures"]
    assert f["stable"] and f["phase_margin_deg"] >= 50.0 and f["gain_margin_db"] >= 8.0, f
    assert f["ringing_pct"] <= 0.5, f
    assert r["feedback"]["kp"] > 0.0 and r["feedback"]["ki"] > 0.0, r["feedback"]
    # The sweep ran at the board's rate, and the board's own gains were judged beside.
    assert r["rate_hz"] == 50000.0 and len(r["points"]) > 20
    assert r["before"]["feedback"] == before
    # Nothing loaded: the board keeps its gains, in the mode it was in.
    assert r["loaded"] is False
    assert board.params()["feedback"] == before
    assert board.status()["mode"] == "bypass"
    # The stage's resonance as the command line fits it (the simulated stage's 21.8 kHz).
    cli = _cli_tune(hal_sim, "--phase-margin", "50", "--gain-margin", "8")
    assert r["fit"]["resonance_hz"] == pytest.approx(cli["fit"]["resonance_hz"], rel=0.002)
    assert r["fit"]["resonance_hz"] == pytest.approx(21_800.0, rel=0.01)
    assert r["fit"]["zeta"] == pytest.approx(cli["fit"]["zeta"], rel=0.05)
    # The command's object, from the same library function.
    assert set(r) == set(cli) and set(r["fit"]) == set(cli["fit"])


def test_tune_with_load_puts_the_gains_on_the_board(board):
    r = board.tune(load=True)
    assert r["loaded"] is True
    fb = board.params()["feedback"]
    assert fb["kp"] == pytest.approx(r["feedback"]["kp"], rel=1e-6)
    assert fb["ki"] == pytest.approx(r["feedback"]["ki"], rel=1e-6)
    assert fb["limit"] == pytest.approx(r["feedback"]["limit"], rel=1e-6)
    assert board.get("/feedback/kp") == fb["kp"] and fb["kp"] > 0.0
    assert board.status()["mode"] == "bypass", "the sweep's mode is restored"


def test_tune_checks_a_given_gain_set_and_refuses_one_the_fitted_model_says_is_unstable(board, hal_sim):
    r = board.tune(kp=0.2, ki=3000.0, notch_hz=21800.0, notch_q=1.0, notch_depth=0.1)
    assert r["feedback"]["kp"] == 0.2 and r["feedback"]["ki"] == 3000.0
    assert r["feedback"]["notch"] == {"frequency_hz": 21800.0, "q": 1.0, "depth": 0.1}
    assert r["feedback"]["limit"] == 0.25 and r["loaded"] is False
    f = r["figures"]
    assert f["stable"] and f["phase_margin_deg"] >= 45.0 and f["gain_margin_db"] >= 6.0, f
    # The figures the command line gives for the same set.
    cli = _cli_tune(
        hal_sim, "--kp", "0.2", "--ki", "3000", "--notch-hz", "21800", "--notch-q", "1",
        "--notch-depth", "0.1",
    )
    assert cli["feedback"] == r["feedback"]
    assert f["phase_margin_deg"] == pytest.approx(cli["figures"]["phase_margin_deg"], abs=1.0)
    assert f["gain_margin_db"] == pytest.approx(cli["figures"]["gain_margin_db"], abs=0.5)
    before = board.params()["feedback"]
    with pytest.raises(ValueError, match=r"kp 1\.5, ki 20000(\.0)?: refused: unstable"):
        board.tune(kp=1.5, ki=20000.0, load=True)
    assert board.params()["feedback"] == before, "nothing was loaded"


def test_tune_refuses_bad_arguments_before_anything_moves():
    with twinstack.Board("sim") as board:
        ticks = board.status()["ticks"]
        with pytest.raises(ValueError, match="kp and ki"):
            board.tune(kp=0.2)
        with pytest.raises(ValueError, match="kp and ki"):
            board.tune(ki=3000.0)
        with pytest.raises(ValueError, match="notch_hz"):
            board.tune(notch_hz=21800.0)
        with pytest.raises(ValueError, match="phase_margin -1"):
            board.tune(phase_margin=-1.0)
        with pytest.raises(ValueError, match="gain_margin NaN"):
            board.tune(gain_margin=float("nan"))
        with pytest.raises(ValueError, match="phase_margin inf"):
            board.tune(phase_margin=float("inf"))
        # A gain set the board refuses at its rate (ki below half the 50 kHz tick rate).
        with pytest.raises(ValueError, match="feedback.ki"):
            board.tune(kp=0.2, ki=30000.0)
        # The simulated board's time runs only while a call waits on it: a sweep is thousands
        # of ticks, these were a status request or none.
        assert board.status()["ticks"] - ticks < 200


def test_a_sequence_steps_one_position_per_camera_frame_and_counts_early_and_missed():
    # A 200-position Z stack on the simulated camera's edges, each exposure started by the
    # settled output: every position reached, none early, none missed, and the edge's own
    # tick writes the first moved DAC sample.
    z = np.concatenate([np.linspace(-0.1, 0.05, 100), np.linspace(0.05, -0.1, 100)])
    with twinstack.Board(
        "sim", sim_camera_hz=1000.0, sim_camera_frames=200, sim_camera_on_settled=True
    ) as b:
        r = b.sequence(z, window=0.05, settle_ticks=25, normalised=True, mode="closed-loop")
        assert (r["steps"], r["early"], r["missed"], r["complete"]) == (200, 0, 0, True)
        assert r["ticks_to_motion"] == 0
        assert "sequence" not in b.status()["flags"], "disarmed at the end"
    # Free-running at 10 kHz (5 ticks a frame) against a 25-tick settle time, 10 frames more
    # than positions: every edge early, the last ten missed.
    with twinstack.Board("sim", sim_camera_hz=10000.0, sim_camera_frames=210) as b:
        r = b.sequence(z, window=0.05, settle_ticks=25, normalised=True, idle=0.05)
        assert r["steps"] == 200 and r["early"] >= 200
        assert r["missed"] <= 10


def test_a_bad_sequence_is_refused_before_anything_moves():
    with twinstack.Board("sim") as b:
        with pytest.raises(ValueError, match="positions\\[1\\]"):
            b.sequence([0.1, float("nan")], normalised=True)
        with pytest.raises(ValueError, match="sequence window"):
            b.sequence([0.1], window=2.0, normalised=True)
        with pytest.raises(ValueError, match="edge"):
            b.sequence([0.1], edge="up", normalised=True)
        assert b.status()["queue_fill"] == 0
    with pytest.raises(ValueError, match="only with port"):
        twinstack.Board("tcp:127.0.0.1:1", sim_camera_hz=100.0)
    # The camera's options without its frame rate: refused, not ignored.
    for options in ({"sim_camera_frames": 5}, {"sim_camera_on_settled": True}):
        with pytest.raises(ValueError, match="sim_camera_hz"):
            twinstack.Board("sim", **options)


def test_the_analog_input_starts_reports_and_stops(board):
    # The in-process board's input pin has nothing wired to it: the input is lost and the
    # output holds where it was.
    board.analog(gain=2.0, offset=-1.0, corner_hz=500.0, lost_below=0.02, rate=5.0)
    flags = board.status()["flags"]
    assert "analog" in flags and "analog-fault" in flags, flags
    a = board.analog_status()
    assert a["running"] and a["lost"] and not a["over_range"], a
    assert a["faults"] == 1, a
    # Another source is refused while it runs, and the board says why.
    with pytest.raises(twinstack.BoardError, match="busy"):
        board.waveform(amplitude=0.5, frequency=50.0)
    board.stop()
    assert not board.analog_status()["running"]
    assert "analog" not in board.status()["flags"]


def test_analog_settings_are_refused_before_sending(board):
    with pytest.raises(ValueError, match="analog gain is NaN"):
        board.analog(gain=float("nan"))
    with pytest.raises(ValueError, match="on_fault"):
        board.analog(on_fault="jump")
    assert not board.analog_status()["running"], "nothing was sent"


def test_settings_by_path(board):
    schema = dict(twinstack.settings_schema())
    assert schema["/drive/slew_rate"] == "f64"
    assert "ClosedLoop" in schema["/mode"]
    assert board.set("/drive/slew_rate", 2000.0) == 2000.0
    assert board.get("/drive/slew_rate") == 2000.0
    assert board.set("/mode", "ClosedLoop") == "ClosedLoop"
    assert board.params()["mode"] == "ClosedLoop"
    with pytest.raises(KeyError, match="has no `slew`"):
        board.get("/drive/slew")
    with pytest.raises(ValueError, match="/drive/slew_rate"):
        board.set("/drive/slew_rate", "fast")
    with pytest.raises(twinstack.BoardError, match="max_voltage"):
        board.set("/drive/max_voltage", 1000.0)
    assert board.get("/drive/slew_rate") == 2000.0
    # numpy's numbers are numbers; NaN, infinity and a number beyond f64 are refused naming
    # the path, with nothing changed.
    assert board.set("/drive/slew_rate", np.float32(1500.0)) == 1500.0
    assert board.set("/drive/slew_rate", np.int64(2000)) == 2000.0
    for bad in (float("nan"), np.inf, 10**400):
        with pytest.raises(ValueError, match="/drive/slew_rate"):
            board.set("/drive/slew_rate", bad)
    assert board.get("/drive/slew_rate") == 2000.0


# A Bouc–Wen model over the board's default 0…140 V, 0…70 µm (the library's representative
# one) and a flexure's output map after it: 6 % flatter toward either end, three dead zones a
# side (the library's representative map).
BOUC_WEN = {
    "BoucWen": {
        "k": 0.42,
        "offset": 0.0,
        "a": 0.1,
        "beta": 0.04,
        "gamma": 0.008,
        "psi": 0.006,
        "chi": 0.0,
    }
}
FLEXURE_MAP = {
    "centre": 35.0,
    "linear": 1.0,
    "thresholds": [-30.0, -20.0, -10.0, 10.0, 20.0, 30.0],
    "weights": [-0.03, -0.02, -0.01, -0.01, -0.02, -0.03],
}


def test_an_output_map_loads_from_a_file_and_is_reached_by_its_paths(board):
    settings = board.params()
    settings.update(compensator=BOUC_WEN, observer=BOUC_WEN, mode="OpenLoop", output_map=None)
    board.load(twinstack.Params.from_json(param_json(settings)))
    assert board.get("/output_map") is None
    with pytest.raises(KeyError, match="`/output_map` is not set"):
        board.set("/output_map/linear", 1.01)
    settings["output_map"] = FLEXURE_MAP
    params = twinstack.Params.from_json(param_json(settings))
    assert params.settings["output_map"] == FLEXURE_MAP
    board.load(params)
    assert board.params()["output_map"] == FLEXURE_MAP
    assert board.get("/output_map/linear") == 1.0
    assert board.set("/output_map/linear", 1.01) == 1.01
    assert board.set("/output_map/weights/5", -0.04) == -0.04
    held = board.params()["output_map"]
    assert held["linear"] == 1.01 and held["weights"][5] == -0.04
    assert held["thresholds"] == FLEXURE_MAP["thresholds"]
    # A map that falls is refused by the board, naming the map's field; nothing changes.
    with pytest.raises(twinstack.BoardError, match="output_map"):
        board.set("/output_map/weights/5", -1.5)
    assert board.get("/output_map/weights/5") == -0.04
    assert board.set("/output_map", None) is None
    assert board.params()["output_map"] is None
