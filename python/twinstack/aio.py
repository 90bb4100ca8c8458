"""asyncio API of a twinstack board, beside the blocking :class:`twinstack.Board`.

:class:`AsyncBoard` runs each of the native board's calls in a worker thread of its own (the
native calls release the interpreter's lock while they wait on the board), so a long call
never blocks the event loop: other coroutines -- a status poll, a GUI, a second board -- run
while a stream plays or a capture fills.

Semantics, which a caller can rely on:

* **One request at a time per board, in order.** Calls on one :class:`AsyncBoard` queue on an
  :class:`asyncio.Lock` (first come, first served) instead of failing as two threads sharing
  a :class:`~twinstack.Board` do. A call that is waiting for its turn can be cancelled freely.
* **A stream leaves room for other calls.** :meth:`AsyncBoard.stream` sends its setpoints in
  chunks (by default 0.5 s of setpoints, at most one setpoint queue's worth) and lets
  go of the board between two chunks, so a :meth:`~AsyncBoard.status` poll is answered within
  one chunk while the stream plays; the board's queue is topped up again right after it.
  Underruns, if a host is too slow for that, are counted in the report as always.
* **Cancellation is clean.** A native call cannot be interrupted half way (the link would be
  left mid-request), so a cancelled call waits for the call in flight to finish before the
  :class:`asyncio.CancelledError` goes up: the board is free and its line clean for the next
  call. A cancelled stream also tells the board to stop (what is queued stays queued, as
  after ``twinstack stop``), so it stops within one chunk.

numpy in and out as the blocking API: the same arguments, the same dicts of float64 arrays,
the same exceptions (:class:`~twinstack.BoardError`, ``TimeoutError``, ...).

>>> import asyncio, numpy as np, twinstack
>>> async def main():
...     async with await twinstack.AsyncBoard.open("sim") as board:
...         report = await board.stream(np.zeros(100), rate=5000.0)
...         return report["accepted"], (await board.status())["mode"]
>>> asyncio.run(main())
(100, 'bypass')
"""

import asyncio
import concurrent.futures
import functools
from typing import Any, Callable, Dict, Optional, Sequence, Tuple, TypeVar, Union

import numpy as np

from ._native import Board, Params
from ._native import identify as _identify

T = TypeVar("T")

#: Seconds of setpoints :meth:`AsyncBoard.stream` sends per chunk by default (at most one
#: setpoint queue's worth): how long another call on the board waits at most during a stream.
#: Each chunk costs a few round trips (two statuses and its batches: about 0.1 s through a
#: USB–serial adapter's 16 ms each way, more with other calls in between), so a chunk must
#: play for longer than that, or the queue runs dry between chunks.
CHUNK_SECONDS = 0.5

__all__ = ["AsyncBoard", "identify"]


async def _finish(future: "asyncio.Future[T]") -> T:
    """Awaits `future` (a call running in a thread); if the awaiting task is cancelled, waits
    until the thread's call has returned anyway, then lets the cancellation go up."""
    try:
        return await asyncio.shield(future)
    except asyncio.CancelledError:
        while not future.done():
            try:
                await asyncio.wait([future])
            except asyncio.CancelledError:
                continue
        raise


class AsyncBoard:
    """A board driven from asyncio: :meth:`open` it (or wrap a :class:`~twinstack.Board`),
    ``await`` its methods, ``async with`` to close it."""

    def __init__(self, board: Board) -> None:
        self._board = board
        self._lock = asyncio.Lock()
        self._worker = concurrent.futures.ThreadPoolExecutor(
            max_workers=1, thread_name_prefix=f"twinstack {board.port}"
        )
        self._closed = False

    @classmethod
    async def open(cls, port: str, baud: int = 2_000_000, timeout: float = 2.0) -> "AsyncBoard":
        """Connects to the board at `port` (as :class:`~twinstack.Board`) without blocking the
        event loop."""
        loop = asyncio.get_running_loop()
        board = await loop.run_in_executor(None, functools.partial(Board, port, baud, timeout))
        return cls(board)

    @property
    def board(self) -> Board:
        """The blocking board underneath (do not call it while an ``await`` on this one runs)."""
        return self._board

    @property
    def port(self) -> str:
        """The port the board was opened on."""
        return self._board.port

    async def _call(self, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        if self._closed:
            # The closed board answers at once, as the blocking one does ("the board is
            # closed"): its worker thread is gone.
            return fn(*args, **kwargs)
        async with self._lock:
            loop = asyncio.get_running_loop()
            future = loop.run_in_executor(self._worker, functools.partial(fn, *args, **kwargs))
            return await _finish(future)

    async def status(self) -> Dict[str, Any]:
        """Status and telemetry counters, as :meth:`twinstack.Board.status`."""
        return await self._call(self._board.status)

    async def params(self) -> Dict[str, Any]:
        """The settings in force, as :meth:`twinstack.Board.params`."""
        return await self._call(self._board.params)

    async def get(self, path: str) -> Any:
        """One setting by its path, as :meth:`twinstack.Board.get`."""
        return await self._call(self._board.get, path)

    async def set(self, path: str, value: Any) -> Any:
        """Changes one setting by its path, as :meth:`twinstack.Board.set`."""
        return await self._call(self._board.set, path, value)

    async def mode(self, mode: str) -> None:
        """Switches the control mode, as :meth:`twinstack.Board.mode`."""
        await self._call(self._board.mode, mode)

    async def load(
        self,
        params: Params,
        clamp: bool = False,
        mode: Optional[str] = None,
        store: Optional[str] = None,
        preview: Optional[bool] = None,
    ) -> None:
        """Loads a parameter file's settings, as :meth:`twinstack.Board.load`."""
        await self._call(self._board.load, params, clamp, mode, store, preview)

    async def stop(self) -> None:
        """Stops the stream or the waveform; the output holds."""
        await self._call(self._board.stop)

    async def waveform(
        self, amplitude: float, frequency: float, shape: str = "sine", offset: float = 0.0
    ) -> None:
        """Starts the board's waveform generator, as :meth:`twinstack.Board.waveform`."""
        await self._call(self._board.waveform, amplitude, frequency, shape, offset)

    async def arm(
        self,
        signals: Union[str, Sequence[str]],
        samples: int,
        trigger: str = "now",
        pre: int = 0,
        decimation: int = 1,
    ) -> None:
        """Arms a capture without waiting for it, as :meth:`twinstack.Board.arm`."""
        await self._call(self._board.arm, signals, samples, trigger, pre, decimation)

    async def fetch(self, timeout: float = 30.0) -> Dict[str, np.ndarray]:
        """Waits for the armed capture and reads it back, as :meth:`twinstack.Board.fetch`."""
        return await self._call(self._board.fetch, timeout)

    async def coarse_home(self, wait: bool = True, timeout: float = 120.0) -> Dict[str, Any]:
        """Homes the coarse axis, as :meth:`twinstack.Board.coarse_home`."""
        return await self._call(self._board.coarse_home, wait, timeout)

    async def coarse_move(
        self,
        to_mm: float,
        speed: float = 10.0,
        accel: float = 200.0,
        wait: bool = True,
        timeout: float = 120.0,
    ) -> Dict[str, Any]:
        """Moves the coarse axis, as :meth:`twinstack.Board.coarse_move`."""
        return await self._call(self._board.coarse_move, to_mm, speed, accel, wait, timeout)

    async def coarse_jog(self, speed: float) -> None:
        """Jogs the coarse axis, as :meth:`twinstack.Board.coarse_jog`."""
        await self._call(self._board.coarse_jog, speed)

    async def coarse_stop(self) -> None:
        """Stops the coarse axis, as :meth:`twinstack.Board.coarse_stop`."""
        await self._call(self._board.coarse_stop)

    async def coarse_release(self) -> None:
        """Hands the piezo back from the coarse axis, as :meth:`twinstack.Board.coarse_release`."""
        await self._call(self._board.coarse_release)

    async def coarse_status(self) -> Dict[str, Any]:
        """The coarse axis's status, as :meth:`twinstack.Board.coarse_status`."""
        return await self._call(self._board.coarse_status)

    async def learn(
        self,
        period_ticks: int,
        gain: float = 0.3,
        cutoff_hz: float = 3000.0,
        lead_ticks: int = 1,
        limit: float = 0.25,
        reset: bool = True,
    ) -> None:
        """Starts the learning feedforward, as :meth:`twinstack.Board.learn`."""
        await self._call(
            self._board.learn, period_ticks, gain, cutoff_hz, lead_ticks, limit, reset
        )

    async def learn_state(self, state: str) -> None:
        """Switches the learning, as :meth:`twinstack.Board.learn_state`."""
        await self._call(self._board.learn_state, state)

    async def learn_status(self) -> Dict[str, Any]:
        """The learning's state, as :meth:`twinstack.Board.learn_status`."""
        return await self._call(self._board.learn_status)

    async def learn_table(self) -> np.ndarray:
        """The learned table, as :meth:`twinstack.Board.learn_table`."""
        return await self._call(self._board.learn_table)

    async def learn_load_table(self, table: Any) -> None:
        """Plays a kept table again, as :meth:`twinstack.Board.learn_load_table`."""
        await self._call(self._board.learn_load_table, table)

    async def scan(
        self,
        pattern: str,
        ticks_per_pixel: int = 4,
        frames: int = 1,
        pulse: int = 2,
        timeout: float = 60.0,
        start_on: str = "now",
    ) -> Dict[str, Any]:
        """Runs a scan pattern on the board with its clocks, as :meth:`twinstack.Board.scan`."""
        return await self._call(
            self._board.scan, pattern, ticks_per_pixel, frames, pulse, timeout, start_on
        )

    async def telemetry(
        self,
        signals: Union[str, Sequence[str]],
        rate: float = 10000.0,
        seconds: float = 1.0,
    ) -> Dict[str, Any]:
        """Continuous telemetry for `seconds` of samples, as :meth:`twinstack.Board.telemetry`."""
        return await self._call(self._board.telemetry, signals, rate, seconds)

    async def record(
        self,
        signals: Union[str, Sequence[str]],
        samples: int,
        trigger: str = "now",
        pre: int = 0,
        decimation: int = 1,
        timeout: float = 30.0,
    ) -> Dict[str, np.ndarray]:
        """Records several signals at once, as :meth:`twinstack.Board.record`."""
        return await self._call(
            self._board.record, signals, samples, trigger, pre, decimation, timeout
        )

    async def store(self, boot_mode: str = "bypass") -> None:
        """Writes the settings in force to flash, as :meth:`twinstack.Board.store`."""
        await self._call(self._board.store, boot_mode)

    async def recall(self) -> None:
        """Reloads the stored settings, as :meth:`twinstack.Board.recall`."""
        await self._call(self._board.recall)

    async def calibrate(
        self,
        store: bool = True,
        clamp: bool = False,
        model: Optional[str] = None,
        resonance: bool = True,
        fastest_hz: Optional[float] = None,
    ) -> Dict[str, Any]:
        """Calibrates the stage in one call, as :meth:`twinstack.Board.calibrate`."""
        return await self._call(
            self._board.calibrate, store, clamp, model, resonance, fastest_hz
        )

    async def tune(
        self,
        phase_margin: float = 45.0,
        gain_margin: float = 6.0,
        load: bool = False,
        kp: Optional[float] = None,
        ki: Optional[float] = None,
        notch_hz: Optional[float] = None,
        notch_q: float = 2.0,
        notch_depth: float = 0.0,
        limit: float = 0.25,
        progress: Optional[Callable[[Dict[str, float]], Any]] = None,
    ) -> Dict[str, Any]:
        """Measures the stage's response, fits it and designs (or checks) the feedback, as
        :meth:`twinstack.Board.tune`. ``progress`` is called in the worker thread, not in the
        event loop's."""
        return await self._call(
            self._board.tune,
            phase_margin,
            gain_margin,
            load,
            kp,
            ki,
            notch_hz,
            notch_q,
            notch_depth,
            limit,
            progress,
        )

    async def sequence(
        self,
        positions: Any,
        window: float = 0.005,
        settle_ticks: int = 25,
        edge: str = "rising",
        normalised: bool = False,
        mode: Optional[str] = None,
        idle: float = 5.0,
    ) -> Dict[str, Any]:
        """Runs a TTL-stepped sequence, as :meth:`twinstack.Board.sequence`."""
        return await self._call(
            self._board.sequence, positions, window, settle_ticks, edge, normalised, mode, idle
        )

    async def shaped(
        self,
        setpoints: Any,
        resonance: Optional[Tuple[float, float]],
        rate: Optional[float] = None,
        normalised: bool = False,
    ) -> np.ndarray:
        """The setpoints a stream would send, normalised, shaped for `resonance`, as
        :meth:`twinstack.Board.shaped`; nothing is sent."""
        return await self._call(self._board.shaped, setpoints, resonance, rate, normalised)

    async def stream(
        self,
        setpoints: Any,
        rate: Optional[float] = None,
        normalised: bool = False,
        underrun: Optional[str] = None,
        wait: bool = True,
        chunk: Optional[int] = None,
        resonance: Optional[Tuple[float, float]] = None,
        start_on: str = "now",
        edge_timeout: float = 60.0,
    ) -> Dict[str, Any]:
        """Streams `setpoints` as :meth:`twinstack.Board.stream` does, in chunks of `chunk`
        setpoints (default: :data:`CHUNK_SECONDS` of them, at most the board's setpoint queue),
        letting other
        calls on this board in between two chunks. Returns the blocking call's report summed
        over the chunks (``accepted``, ``batches``, ``underruns``, ``seconds``, ...) plus
        ``chunks``. The chunks play as one stream (each but the last sent with ``more``, see
        :meth:`twinstack.Board.stream`): each is queued behind the one still playing, with no
        stop between them. With ``wait=True`` ``underruns`` counts the board's empty ticks over
        the whole stream, between the chunks too; with ``wait=False`` it is the chunks' own
        counts summed, which miss the gaps between them. Cancelled, it tells the board to stop and raises
        ``CancelledError``.
        `resonance` shapes the whole trajectory first (:meth:`twinstack.Board.shaped`, before
        it is cut into chunks: the shaping of a setpoint needs the two after it), as
        ``Board.stream(…, resonance=…)`` does. `start_on` and `edge_timeout`: the first chunk
        waits for the trigger input's edge, as ``Board.stream(…, start_on=…)`` does."""
        values = np.asarray(setpoints)
        if values.ndim != 1:
            raise ValueError(f"setpoints must be one-dimensional, got shape {values.shape}")
        if values.size == 0:
            raise ValueError("setpoints is empty")
        # The whole trajectory is converted (and with `resonance` shaped) before the first
        # chunk is sent: a bad setpoint anywhere is refused, naming its index in it, with
        # nothing sent, as the blocking call refuses it.
        values = await self.shaped(values, resonance, rate, normalised)
        normalised = True
        if chunk is None:
            s = await self.status()
            per_second = rate if rate is not None else float(s["tick_rate_hz"])
            queue = int(s["queue_fill"]) + int(s["credits"])
            chunk = max(1, min(queue, int(CHUNK_SECONDS * per_second)))
        elif chunk < 1:
            raise ValueError(f"chunk {chunk}: must be at least 1 setpoint")
        total: Dict[str, Any] = {}
        starts = range(0, values.size, chunk)
        # The board's underrun counter over the whole stream: between two chunks it plays on,
        # and what it counts there is in neither chunk's report.
        underruns_before = int((await self.status())["underruns"])
        try:
            for i, start in enumerate(starts):
                last = i == len(starts) - 1
                part = values[start : start + chunk]
                report = await self._call(
                    self._board.stream,
                    part,
                    rate,
                    normalised,
                    underrun,
                    wait and last,
                    None,
                    not last,
                    start_on if i == 0 else "now",
                    edge_timeout,
                )
                _add_report(total, report)
        except asyncio.CancelledError:
            await asyncio.shield(self._stop_after_cancel())
            raise
        total["chunks"] = len(starts)
        if wait:
            # Drained: the board stopped at the stream's end and counts no more.
            counted = (int((await self.status())["underruns"]) - underruns_before) % 2**32
            total["underruns"] = counted
            total["underran"] = counted != 0
        return total

    async def _stop_after_cancel(self) -> None:
        async with self._lock:
            loop = asyncio.get_running_loop()
            await loop.run_in_executor(self._worker, self._board.stop)

    async def close(self) -> None:
        """Closes the link once the call in flight has returned; closing it again does
        nothing, as :meth:`twinstack.Board.close`."""
        if self._closed:
            return
        await self._call(self._board.close)
        self._closed = True
        self._worker.shutdown(wait=False)

    async def __aenter__(self) -> "AsyncBoard":
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.close()

    def __repr__(self) -> str:
        return f"AsyncBoard({self.port!r})"


def _add_report(total: Dict[str, Any], report: Dict[str, Any]) -> None:
    """Folds one chunk's stream report into the running total."""
    for key, value in report.items():
        if key not in total:
            total[key] = value
        elif key in ("divider", "drained"):
            total[key] = value
        elif key == "underran":
            total[key] = bool(total[key] or value)
        elif key == "underruns":
            total[key] = None if total[key] is None or value is None else total[key] + value
        else:
            total[key] = total[key] + value


async def identify(*args: Any, **kwargs: Any) -> Params:
    """:func:`twinstack.identify` in a worker thread: the event loop runs while it fits."""
    loop = asyncio.get_running_loop()
    return await loop.run_in_executor(None, functools.partial(_identify, *args, **kwargs))
