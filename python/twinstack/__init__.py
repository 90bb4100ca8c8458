"""twinstack: the lab's Python interface to a twinstack piezo board.

Built from the project's own host library (``hal-sim``) with PyO3: the same protocol client,
in-process simulated board, identification and parameter file as the ``hal-sim`` command line.

* :class:`Board` -- a board on a serial port, ``tcp:HOST:PORT`` (a virtual board, QEMU) or
  ``"sim"`` (the simulated board in-process): status, load, params, mode, stream, waveform,
  record, store, recall.
* :func:`identify` -- a hysteresis model from a measured record, as a :class:`Params`
  (predict, compensate, save); :func:`load_params` reads a parameter file back.
* :class:`BoardError` -- a refusal, with the field, the reason and the limit the board named.
"""

from ._native import Board, BoardError, Params, identify, load_params

__all__ = ["Board", "BoardError", "Params", "identify", "load_params"]
__version__ = "0.1.0"
