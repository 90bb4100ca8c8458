"""bluesky devices for a twinstack board: plain Python objects that implement bluesky's
duck-typed protocols, so a :class:`bluesky.RunEngine` runs them with no EPICS and no ophyd.

* :class:`Axis` -- ``Movable`` and ``Readable`` (and ``Configurable``, ``Stoppable``,
  ``HasHints``, ``Locatable``): ``set(x)`` streams the target to the board and returns a
  :class:`Status` that completes when the sensor has stayed within ``window`` of it for
  ``settle_time``; ``read()`` gives the sensor reading (the axis' position), the setpoint and
  the error, averaged over a short recording, with timestamps.
* :class:`CoarseAxis` -- the dual-actuated stage's coarse axis (millimetres of travel on a
  ball screw) as a ``Movable`` and ``Readable``: ``set(mm)`` moves it and completes once it
  has come to rest there; ``read()`` gives its position, setpoint and following error.
* :class:`Flyer` -- ``Flyable`` and ``EventCollectable``: ``kickoff()`` arms the board's recorder
  on the stream's start and plays a trajectory (:meth:`Flyer.raster` builds a serpentine
  raster of lines and pixels), ``complete()`` finishes when it has played and the recording
  is read back, ``collect()`` yields one event per recorded sample (per pixel of a raster):
  setpoint, sensor, error, line and pixel, each timestamped from the board's own clock.
* :class:`ScanFlyer` -- the same protocols over a scan the board generates itself
  (:meth:`twinstack.Board.scan`: a raster, a Lissajous or a spiral, with its pixel, line and
  frame trigger outputs for a detector to follow): one event per pixel clock, with the
  position the board commanded at it, its frame, line and pixel, timestamped from the board's
  clock.

Nothing here imports bluesky: the devices only follow its protocols
(``bluesky.protocols``), as ophyd's do. The board calls block, so each device runs them in a
thread of its own and serialises them on a lock: ``read`` during a ``set`` waits for it
rather than failing.

>>> import twinstack
>>> from twinstack.bluesky import Axis
>>> board = twinstack.Board("sim")
>>> board.load(board.calibrate(store=False)["params"], mode="closed-loop")
>>> x = Axis(board, name="x", window=0.2)
>>> x.set(10.0).wait(10.0)
>>> abs(x.read()["x"]["value"] - 10.0) < 0.2
True
"""

import threading
import time
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import numpy as np

from ._native import Board

__all__ = ["Axis", "CoarseAxis", "Flyer", "ScanFlyer", "Status", "SettleTimeout"]


class SettleTimeout(TimeoutError):
    """A move whose sensor did not settle within the window in time."""


class Status:
    """A bluesky ``Status``: done once, successful or with an exception; callbacks run once it
    is done (at once if it already is). Thread-safe."""

    def __init__(self, obj: Any = None) -> None:
        self.obj = obj
        self._event = threading.Event()
        self._lock = threading.Lock()
        self._callbacks: List[Callable[["Status"], None]] = []
        self._exception: Optional[BaseException] = None

    @property
    def done(self) -> bool:
        """Whether it has finished, either way."""
        return self._event.is_set()

    @property
    def success(self) -> bool:
        """Whether it finished without an exception."""
        return self.done and self._exception is None

    def exception(self, timeout: Optional[float] = 0.0) -> Optional[BaseException]:
        """The exception it finished with (``None`` on success); waits up to `timeout`
        seconds (``None``: as long as it takes) and raises ``TimeoutError`` if not done."""
        if not self._event.wait(timeout):
            raise TimeoutError("the status is not done")
        return self._exception

    def wait(self, timeout: Optional[float] = None) -> None:
        """Waits until done; raises the exception it finished with."""
        exc = self.exception(timeout)
        if exc is not None:
            raise exc

    def add_callback(self, callback: Callable[["Status"], None]) -> None:
        """Calls `callback(status)` once it is done."""
        with self._lock:
            if not self.done:
                self._callbacks.append(callback)
                return
        callback(self)

    def _finish(self, exception: Optional[BaseException] = None) -> None:
        with self._lock:
            if self.done:
                return
            self._exception = exception
            self._event.set()
            callbacks, self._callbacks = self._callbacks, []
        for cb in callbacks:
            cb(self)

    def __repr__(self) -> str:
        state = "running" if not self.done else ("done" if self.success else "failed")
        return f"Status({state}, {self._exception!r})"


def _run(status: Status, work: Callable[[], None]) -> Status:
    """Runs `work` in a thread; its return finishes `status`, its exception fails it."""

    def target() -> None:
        try:
            work()
        except BaseException as e:  # noqa: BLE001 -- handed to the status, not swallowed
            status._finish(e)
        else:
            status._finish()

    threading.Thread(target=target, daemon=True, name=f"twinstack {status.obj}").start()
    return status


def _key(source: str, units: Optional[str] = None, precision: int = 4) -> Dict[str, Any]:
    d: Dict[str, Any] = {"source": source, "dtype": "number", "shape": [], "precision": precision}
    if units is not None:
        d["units"] = units
    return d


class _Positioner:
    """What the axes share: the last target, where the axis is, and the field a plot shows.
    :meth:`read` gives the position under the axis' name and its setpoint as ``<name>_setpoint``."""

    name: str
    _target: Optional[float]

    def read(self) -> Dict[str, Dict[str, Any]]:
        raise NotImplementedError

    @property
    def position(self) -> Optional[float]:
        """The last target set (``None`` before the first ``set``)."""
        return self._target

    def locate(self) -> Dict[str, float]:
        """``{"setpoint": ..., "readback": ...}``: the setpoint and the position now."""
        r = self.read()
        return {"setpoint": r[f"{self.name}_setpoint"]["value"], "readback": r[self.name]["value"]}

    @property
    def hints(self) -> Dict[str, List[str]]:
        """The field a plot shows: the position."""
        return {"fields": [self.name]}


class Axis(_Positioner):
    """The board's axis as a bluesky ``Movable`` and ``Readable``, in the output unit of the
    settings in force (µm for the simulated board).

    `window` is the settle window (in the output unit): a move is done once the sensor has
    stayed within it of the target for `settle_time` seconds, checked on recordings of
    `settle_time` each, for at most `timeout` seconds (then the status fails with
    :class:`SettleTimeout` naming the last error). A move streams the target at `rate`
    setpoints per second for `hold` seconds; the board's slew limit shapes the step, and the
    output then holds. The sensor settles on the target in closed loop (``board.mode
    ("closed-loop")``); in open loop it settles where the compensator puts it.
    """

    def __init__(
        self,
        board: Board,
        name: str = "axis",
        window: float = 0.2,
        settle_time: float = 0.005,
        timeout: float = 10.0,
        rate: float = 5000.0,
        hold: float = 0.01,
        units: str = "um",
        parent: Any = None,
    ) -> None:
        if not (window > 0.0 and settle_time > 0.0 and timeout > 0.0 and hold > 0.0):
            raise ValueError("window, settle_time, timeout and hold must be positive")
        self._board = board
        self.name = name
        self.parent = parent
        self.window = float(window)
        self.settle_time = float(settle_time)
        self.timeout = float(timeout)
        self.rate = float(rate)
        self.hold = float(hold)
        self.units = units
        self._lock = threading.Lock()
        self._target: Optional[float] = None
        self._stopped = threading.Event()
        ranges = board.params()["ranges"]
        self.limits = (float(ranges["output_min"]), float(ranges["output_max"]))
        self.tick_rate = float(board.status()["tick_rate_hz"])

    # -- Movable -------------------------------------------------------------------------

    def set(self, value: float) -> Status:
        """Moves to `value`: a :class:`Status` done when settled within the window. A target
        outside the output range raises ``ValueError`` at once (nothing is sent)."""
        value = float(value)
        lo, hi = self.limits
        if not (np.isfinite(value) and lo <= value <= hi):
            raise ValueError(f"{self.name}: target {value} outside the output range {lo}…{hi}")
        self._target = value
        self._stopped.clear()
        n = max(1, int(round(self.hold * self.rate)))

        def move() -> None:
            with self._lock:
                self._board.stream(np.full(n, value), rate=self.rate)
            self._settle(value)

        return _run(Status(self.name), move)

    def _settle(self, target: float) -> None:
        samples = max(2, int(round(self.settle_time * self.tick_rate)))
        decimation = 1
        while samples > 4096:
            samples //= 2
            decimation *= 2
        deadline = time.monotonic() + self.timeout
        worst = float("inf")
        while True:
            if self._stopped.is_set():
                raise RuntimeError(f"{self.name}: stopped before settling at {target}")
            with self._lock:
                rec = self._board.record(["sensor"], samples=samples, decimation=decimation)
            worst = float(np.max(np.abs(rec["sensor"] - target)))
            if worst <= self.window:
                return
            if time.monotonic() > deadline:
                raise SettleTimeout(
                    f"{self.name}: not settled at {target} {self.units} within ±{self.window} "
                    f"after {self.timeout} s (last {self.settle_time} s: off by up to {worst:.4g})"
                )

    def stop(self, success: bool = True) -> None:
        """Stops the board's stream or waveform (the output holds) and fails a move that is
        still settling."""
        self._stopped.set()
        with self._lock:
            self._board.stop()

    # -- Readable ------------------------------------------------------------------------

    def read(self) -> Dict[str, Dict[str, Any]]:
        """The sensor reading (the axis' position, under the axis' own name), the setpoint
        and the error, each the mean of 0.2 ms recorded on the board, with the time of the
        reading."""
        samples = max(2, int(round(2e-4 * self.tick_rate)))
        with self._lock:
            rec = self._board.record(["setpoint", "sensor", "error"], samples=samples)
        now = time.time()
        return {
            self.name: {"value": float(np.mean(rec["sensor"])), "timestamp": now},
            f"{self.name}_setpoint": {"value": float(np.mean(rec["setpoint"])), "timestamp": now},
            f"{self.name}_error": {"value": float(np.mean(rec["error"])), "timestamp": now},
        }

    def describe(self) -> Dict[str, Dict[str, Any]]:
        """What :meth:`read` gives: three numbers in the output unit."""
        port = self._board.port
        lo, hi = self.limits
        keys = {
            self.name: _key(f"twinstack:{port}:sensor", self.units),
            f"{self.name}_setpoint": _key(f"twinstack:{port}:setpoint", self.units),
            f"{self.name}_error": _key(f"twinstack:{port}:error", self.units),
        }
        keys[self.name]["limits"] = {"control": {"low": lo, "high": hi}}
        return keys

    def read_configuration(self) -> Dict[str, Dict[str, Any]]:
        """The settle window and time, and the board's mode."""
        with self._lock:
            mode = self._board.status()["mode"]
        now = time.time()
        return {
            f"{self.name}_window": {"value": self.window, "timestamp": now},
            f"{self.name}_settle_time": {"value": self.settle_time, "timestamp": now},
            f"{self.name}_mode": {"value": mode, "timestamp": now},
        }

    def describe_configuration(self) -> Dict[str, Dict[str, Any]]:
        """What :meth:`read_configuration` gives."""
        src = f"twinstack:{self._board.port}"
        return {
            f"{self.name}_window": _key(f"{src}:window", self.units),
            f"{self.name}_settle_time": _key(f"{src}:settle_time", "s"),
            f"{self.name}_mode": {"source": f"{src}:mode", "dtype": "string", "shape": []},
        }

    def __repr__(self) -> str:
        return f"Axis({self._board!r}, name={self.name!r}, window={self.window})"


class CoarseAxis(_Positioner):
    """The dual-actuated stage's coarse axis (:meth:`twinstack.Board.coarse_move`) as a
    bluesky ``Movable`` and ``Readable``, in millimetres from the home reference: ``set(mm)``
    moves it at `speed` (mm/s) and `accel` (mm/s²) and completes once it has come to rest
    (within `timeout` seconds); a move the board refuses (not homed, beyond the travel) or
    one that ends in a fault fails the status with the reason. Home it first
    (``board.coarse_home()``)."""

    def __init__(
        self,
        board: Board,
        name: str = "coarse",
        speed: float = 10.0,
        accel: float = 200.0,
        timeout: float = 120.0,
        parent: Any = None,
    ) -> None:
        if not (speed > 0.0 and accel > 0.0 and timeout > 0.0):
            raise ValueError("speed, accel and timeout must be positive")
        self._board = board
        self.name = name
        self.parent = parent
        self.speed = float(speed)
        self.accel = float(accel)
        self.timeout = float(timeout)
        self._lock = threading.Lock()
        self._target: Optional[float] = None

    def set(self, value: float) -> Status:
        """Moves to `value` mm: a :class:`Status` done once the axis is at rest there."""
        value = float(value)
        if not np.isfinite(value):
            raise ValueError(f"{self.name}: target {value} is not a number of millimetres")
        self._target = value

        def move() -> None:
            with self._lock:
                self._board.coarse_move(value, self.speed, self.accel, True, self.timeout)

        return _run(Status(self.name), move)

    def stop(self, success: bool = True) -> None:
        """Brakes the axis to rest (no step lost; still homed)."""
        self._board.coarse_stop()

    def read(self) -> Dict[str, Dict[str, Any]]:
        """Its position (the linear encoder's), setpoint (mm) and following error (µm)."""
        with self._lock:
            s = self._board.coarse_status()
        now = time.time()
        return {
            self.name: {"value": float(s["position_mm"]), "timestamp": now},
            f"{self.name}_setpoint": {"value": float(s["setpoint_mm"]), "timestamp": now},
            f"{self.name}_following_error": {
                "value": float(s["following_error_um"]),
                "timestamp": now,
            },
        }

    def describe(self) -> Dict[str, Dict[str, Any]]:
        """What :meth:`read` gives."""
        src = f"twinstack:{self._board.port}:coarse"
        return {
            self.name: _key(f"{src}:position", "mm", precision=6),
            f"{self.name}_setpoint": _key(f"{src}:setpoint", "mm", precision=6),
            f"{self.name}_following_error": _key(f"{src}:following_error", "um"),
        }

    def read_configuration(self) -> Dict[str, Dict[str, Any]]:
        """The move's speed and acceleration."""
        now = time.time()
        return {
            f"{self.name}_speed": {"value": self.speed, "timestamp": now},
            f"{self.name}_accel": {"value": self.accel, "timestamp": now},
        }

    def describe_configuration(self) -> Dict[str, Dict[str, Any]]:
        """What :meth:`read_configuration` gives."""
        src = f"twinstack:{self._board.port}:coarse"
        return {
            f"{self.name}_speed": _key(f"{src}:speed", "mm/s"),
            f"{self.name}_accel": _key(f"{src}:accel", "mm/s^2"),
        }

    def __repr__(self) -> str:
        return f"CoarseAxis({self._board!r}, name={self.name!r})"


class _BoardFlyer:
    """What the flyers share: the status of the last kickoff's run, and the stop."""

    _board: Board
    name: str
    _played: Optional[Status]

    def complete(self) -> Status:
        """Done once the motion has played and its recording is read back."""
        if self._played is None:
            raise RuntimeError(f"{self.name}: complete() before kickoff()")
        return self._played

    def stop(self, success: bool = True) -> None:
        """Stops the board's motion (the output holds)."""
        self._board.stop()


class Flyer(_BoardFlyer):
    """A trajectory played by the board as a bluesky ``Flyable``: `setpoints` (output unit)
    streamed at `rate` per second, recorded (setpoint, sensor, error) from the stream's
    start, one event every `per_event` setpoints. Before it, the stage is taken to the first
    setpoint and held there for `approach` seconds (not recorded), so the first event is not
    the jump from wherever it was. :meth:`raster` builds a raster.

    With `resonance` (``(frequency_hz, damping)``, ``params.resonance`` as ``calibrate``
    measured it) the trajectory is shaped for the stage's resonance before it is streamed, as
    :meth:`twinstack.Board.stream` shapes it, so that the stage does not ring at its corners
    (a raster's turnarounds): one setpoint a tick (`rate` the board's tick rate), the board in
    open or closed loop. The recorded setpoint and error are then the shaped ones."""

    def __init__(
        self,
        board: Board,
        setpoints: Any,
        rate: float,
        per_event: int = 1,
        name: str = "fly",
        units: str = "um",
        lines: Optional[Sequence[int]] = None,
        pixels: Optional[Sequence[int]] = None,
        parent: Any = None,
        approach: float = 0.05,
        resonance: Optional[Tuple[float, float]] = None,
    ) -> None:
        self._board = board
        self.resonance = resonance
        self.approach = float(approach)
        self.name = name
        self.parent = parent
        self.units = units
        self.setpoints = np.asarray(setpoints, dtype=float)
        if self.setpoints.ndim != 1 or self.setpoints.size == 0:
            raise ValueError("setpoints must be a non-empty one-dimensional array")
        if per_event < 1:
            raise ValueError(f"per_event {per_event}: must be at least 1")
        self.rate = float(rate)
        self.per_event = int(per_event)
        self.events = self.setpoints.size // self.per_event
        self._lines = None if lines is None else np.asarray(lines)
        self._pixels = None if pixels is None else np.asarray(pixels)
        for what, a in (("lines", self._lines), ("pixels", self._pixels)):
            if a is not None and a.size != self.events:
                raise ValueError(f"{what}: {a.size} entries for {self.events} events")
        self._data: Optional[Dict[str, np.ndarray]] = None
        self._t0 = 0.0
        self._played: Optional[Status] = None
        self._report: Optional[Dict[str, Any]] = None
        tick = float(board.status()["tick_rate_hz"])
        divider = tick / self.rate
        if abs(divider - round(divider)) > 1e-9 * divider or divider < 1:
            raise ValueError(f"rate {rate}: not the board's {tick} Hz divided by a whole number")
        self.decimation = int(round(divider)) * self.per_event
        if resonance is not None and int(round(divider)) != 1:
            raise ValueError(
                f"resonance: a shaped trajectory is one setpoint a tick, and rate {rate} is the "
                f"board's {tick} Hz / {int(round(divider))}: pass rate={tick}"
            )
        if self.decimation > 65535:
            raise ValueError(f"per_event {per_event}: one event every {self.decimation} ticks is too long")

    @classmethod
    def raster(
        cls,
        board: Board,
        lines: int = 32,
        pixels: int = 32,
        amplitude: float = 0.5,
        offset: float = 0.0,
        per_pixel: int = 20,
        rate: float = 5000.0,
        name: str = "raster",
        units: str = "um",
        resonance: Optional[Tuple[float, float]] = None,
    ) -> "Flyer":
        """A serpentine raster on the axis: `lines` sweeps across `pixels` pixels, forward then
        back, of `per_pixel` setpoints each at `rate` per second; `amplitude` and `offset`
        normalised (−1…1 over the output range). One event per pixel, with its line and pixel
        number (the slow axis is the line number: another axis steps it). `resonance`: see
        :class:`Flyer`."""
        ranges = board.params()["ranges"]
        lo, hi = float(ranges["output_min"]), float(ranges["output_max"])
        mid, half = (lo + hi) / 2, (hi - lo) / 2
        a, b = mid + half * (offset - amplitude), mid + half * (offset + amplitude)
        if not (lo <= min(a, b) and max(a, b) <= hi):
            raise ValueError(f"raster {a}…{b} outside the output range {lo}…{hi}")
        sweep = np.linspace(a, b, pixels * per_pixel)
        line_list, pixel_list, parts = [], [], []
        for k in range(lines):
            parts.append(sweep if k % 2 == 0 else sweep[::-1])
            line_list.extend([k] * pixels)
            pixel_list.extend(range(pixels) if k % 2 == 0 else range(pixels - 1, -1, -1))
        return cls(
            board,
            np.concatenate(parts),
            rate,
            per_event=per_pixel,
            name=name,
            units=units,
            lines=line_list,
            pixels=pixel_list,
            resonance=resonance,
        )

    # -- Flyable -------------------------------------------------------------------------

    def kickoff(self) -> Status:
        """Takes the stage to the first setpoint, arms the recorder on the stream's start and
        starts the stream: done once it plays."""
        self._data = None
        started = Status(f"{self.name} kickoff")
        played = Status(f"{self.name} complete")
        self._played = played

        def fly() -> None:
            try:
                n = max(1, int(round(self.approach * self.rate)))
                self._board.stream(np.full(n, self.setpoints[0]), rate=self.rate)
                self._board.arm(
                    ["setpoint", "sensor", "error"],
                    samples=self.events,
                    trigger="stream",
                    decimation=self.decimation,
                )
            except BaseException as e:
                started._finish(e)
                raise
            self._t0 = time.time()
            started._finish()
            self._report = self._board.stream(
                self.setpoints, rate=self.rate, resonance=self.resonance
            )
            self._data = self._board.fetch()

        _run(played, fly)
        return started

    @property
    def report(self) -> Optional[Dict[str, Any]]:
        """The stream's report (``accepted``, ``underruns``, ...) once it has played."""
        return self._report

    def describe_collect(self) -> Dict[str, Dict[str, Dict[str, Any]]]:
        """One stream named after the flyer: position (sensor), setpoint, error, line, pixel."""
        src = f"twinstack:{self._board.port}"
        keys = {
            self.name: _key(f"{src}:sensor", self.units),
            f"{self.name}_setpoint": _key(f"{src}:setpoint", self.units),
            f"{self.name}_error": _key(f"{src}:error", self.units),
        }
        if self._lines is not None:
            keys[f"{self.name}_line"] = {"source": f"{src}:line", "dtype": "integer", "shape": []}
        if self._pixels is not None:
            keys[f"{self.name}_pixel"] = {"source": f"{src}:pixel", "dtype": "integer", "shape": []}
        return {self.name: keys}

    def collect(self) -> Iterator[Dict[str, Any]]:
        """One event per recorded sample, timestamped with the kickoff's time plus the
        board's own time from the stream's start."""
        if self._data is None:
            raise RuntimeError(f"{self.name}: collect() before complete() finished")
        d = self._data
        for i in range(len(d["t"])):
            ts = self._t0 + float(d["t"][i])
            data: Dict[str, Any] = {
                self.name: float(d["sensor"][i]),
                f"{self.name}_setpoint": float(d["setpoint"][i]),
                f"{self.name}_error": float(d["error"][i]),
            }
            if self._lines is not None:
                data[f"{self.name}_line"] = int(self._lines[i])
            if self._pixels is not None:
                data[f"{self.name}_pixel"] = int(self._pixels[i])
            yield {"data": data, "timestamps": {k: ts for k in data}, "time": ts}

    @property
    def hints(self) -> Dict[str, List[str]]:
        """The field a plot shows: the position."""
        return {"fields": [self.name]}

    def __repr__(self) -> str:
        return f"Flyer({self._board!r}, name={self.name!r}, events={self.events})"


class ScanFlyer(_BoardFlyer):
    """A scan generated on the board as a bluesky ``Flyable``: `pattern` as
    :meth:`twinstack.Board.scan` takes it (``"raster:lines=32,pixels=64,turn=40"``,
    ``"lissajous:hz=20,x=3,y=2"``, ``"spiral:hz=200,turns=10"``), `ticks_per_pixel`, `frames`
    and the trigger outputs' `pulse` width; `start_on` (``"rising"``, ``"falling"``) makes the
    scan wait for that edge of the board's trigger input. The board plays the pattern from its own clock and
    marks each pixel, line and frame on its trigger outputs, so a detector clocked by them
    needs no host timing; the flyer's events give each pixel's position as the board commanded
    it, one event per pixel clock, with its frame, line and pixel numbers (a raster's pixel
    number is its place along the line, as :meth:`Flyer.raster`'s: its odd lines run back)."""

    def __init__(
        self,
        board: Board,
        pattern: str,
        ticks_per_pixel: int = 4,
        frames: int = 1,
        pulse: int = 2,
        name: str = "scan",
        units: str = "um",
        parent: Any = None,
        timeout: float = 60.0,
        start_on: str = "now",
    ) -> None:
        if frames < 1:
            raise ValueError(f"frames {frames}: a fly scan plays a whole number of frames, at least 1")
        self._board = board
        self.pattern = pattern
        self.ticks_per_pixel = int(ticks_per_pixel)
        self.frames = int(frames)
        self.pulse = int(pulse)
        self.name = name
        self.units = units
        self.parent = parent
        self.timeout = float(timeout)
        self.start_on = start_on
        self._events: Optional[Dict[str, np.ndarray]] = None
        self._figures: Optional[Dict[str, Any]] = None
        self._t0 = 0.0
        self._played: Optional[Status] = None

    def kickoff(self) -> Status:
        """Starts the scan on the board: done once it is asked for (the board checks it first;
        a pattern it refuses fails the status with the refusal)."""
        self._events = None
        started = Status(f"{self.name} kickoff")
        played = Status(f"{self.name} complete")
        self._played = played

        def fly() -> None:
            self._t0 = time.time()
            started._finish()
            run = self._board.scan(
                self.pattern,
                self.ticks_per_pixel,
                self.frames,
                self.pulse,
                self.timeout,
                self.start_on,
            )
            if run["truncated"]:
                raise RuntimeError(
                    f"{self.name}: the board's capture ended before the scan did (its buffer holds "
                    f"{run['t'].size} ticks): fewer frames or pixels"
                )
            self._figures = run["figures"]
            self._events = _pixel_events(run, run["kind"] == "raster")

        _run(played, fly)
        return started

    @property
    def figures(self) -> Optional[Dict[str, Any]]:
        """The scan's timing figures against the library's replay, once it has played."""
        return self._figures

    def describe_collect(self) -> Dict[str, Dict[str, Dict[str, Any]]]:
        """One stream named after the flyer: the commanded position, frame, line, pixel."""
        src = f"twinstack:{self._board.port}"
        integer = lambda what: {"source": f"{src}:{what}", "dtype": "integer", "shape": []}
        return {
            self.name: {
                f"{self.name}_setpoint": _key(f"{src}:setpoint", self.units),
                f"{self.name}_frame": integer("frame"),
                f"{self.name}_line": integer("line"),
                f"{self.name}_pixel": integer("pixel"),
            }
        }

    def collect(self) -> Iterator[Dict[str, Any]]:
        """One event per pixel clock, timestamped with the kickoff's time plus the board's
        own time from the scan's start."""
        if self._events is None:
            raise RuntimeError(f"{self.name}: collect() before complete() finished")
        e = self._events
        for i in range(e["t"].size):
            ts = self._t0 + float(e["t"][i])
            data: Dict[str, Any] = {
                f"{self.name}_setpoint": float(e["setpoint"][i]),
                f"{self.name}_frame": int(e["frame"][i]),
                f"{self.name}_line": int(e["line"][i]),
                f"{self.name}_pixel": int(e["pixel"][i]),
            }
            yield {"data": data, "timestamps": {k: ts for k in data}, "time": ts}

    @property
    def hints(self) -> Dict[str, List[str]]:
        """The field a plot shows: the commanded position."""
        return {"fields": [f"{self.name}_setpoint"]}

    def __repr__(self) -> str:
        return f"ScanFlyer({self._board!r}, {self.pattern!r}, name={self.name!r})"


def _rising(levels: np.ndarray) -> np.ndarray:
    """The ticks where a clock's level rises (a high first tick counts as one)."""
    levels = np.asarray(levels, dtype=bool)
    return np.flatnonzero(levels & ~np.concatenate(([False], levels[:-1])))


def _pixel_events(run: Dict[str, Any], serpentine: bool) -> Dict[str, np.ndarray]:
    """One entry per pixel clock of a :meth:`twinstack.Board.scan` run: its time and commanded
    position, and its frame, line and pixel numbers, counted from the frame and line clocks
    (each line's clock comes before its pixels; the board starts the clocks with the pattern,
    so the approach has none). `serpentine` (a raster): a pixel's number is its place along
    the line, back on odd lines; else its place in time within its line."""
    pixels = _rising(run["pixel"])
    lines = _rising(run["line"])
    frames = _rising(run["frame"])
    # A clock's number at each pixel: the edges at or before it, less one.
    frame = np.searchsorted(frames, pixels, side="right") - 1
    line_total = np.searchsorted(lines, pixels, side="right") - 1
    lines_before_frame = np.searchsorted(lines, frames, side="left")
    line = line_total - lines_before_frame[np.maximum(frame, 0)]
    first_of_line = np.searchsorted(pixels, lines, side="left")
    pixel = np.arange(pixels.size) - first_of_line[np.maximum(line_total, 0)]
    keep = (frame >= 0) & (line_total >= 0)
    if serpentine:
        # The raster's odd lines run back: a pixel's number is its place along the line.
        per_line = np.bincount(line_total[keep], minlength=lines.size)
        odd = keep & (line % 2 == 1)
        pixel[odd] = per_line[line_total[odd]] - 1 - pixel[odd]
    return {
        "t": run["t"][pixels][keep],
        "setpoint": run["setpoint"][pixels][keep],
        "frame": frame[keep],
        "line": line[keep],
        "pixel": pixel[keep],
    }
