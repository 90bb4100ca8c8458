"""twinstack: the lab's Python interface to a twinstack piezo board.

Built from the project's own host libraries (``twinstack-link``, ``twinstack-identify``,
``hal-sim``) with PyO3: the same protocol client,
in-process simulated board, identification and parameter file as the ``twinstack`` command line.

* :class:`Board` -- a board on a serial port, ``tcp:HOST:PORT`` (a virtual board, QEMU) or
  ``"sim"`` (the simulated board in-process): status, load, params, mode, stream, waveform,
  record, telemetry, scan (the board's own patterns and clocks), sequence, analog, learn
  (and the learned table kept and played again), tune (the feedback's gains designed or
  checked on the measured response), the coarse axis of a dual-actuated stage, store, recall.
* :func:`identify` -- a hysteresis model from a measured record, as a :class:`Params`
  (predict, compensate, save); :func:`load_params` reads a parameter file back.
* :class:`BoardError` -- a refusal, with the field, the reason and the limit the board named.
* :class:`AsyncBoard` (:mod:`twinstack.aio`) -- the same board from asyncio: every call
  awaitable, none blocking the event loop; a stream leaves room for a status poll.
* :mod:`twinstack.bluesky` -- an :class:`~twinstack.bluesky.Axis` (Movable, Readable), a
  :class:`~twinstack.bluesky.CoarseAxis` (a dual-actuated stage's coarse axis), a
  :class:`~twinstack.bluesky.Flyer` (Flyable: a raster or any trajectory, streamed) and a
  :class:`~twinstack.bluesky.ScanFlyer` (Flyable: a pattern the board clocks itself) for
  bluesky's RunEngine.
"""

from . import aio
from ._native import Board, BoardError, Params, identify, load_params, settings_schema
from .aio import AsyncBoard

__all__ = [
    "AsyncBoard",
    "Board",
    "BoardError",
    "Params",
    "aio",
    "identify",
    "load_params",
    "settings_schema",
]
__version__ = "0.1.0"
