"""Type stubs of twinstack's extension module (``twinstack._native``).

Arrays in are anything numpy reads as a one-dimensional array of real numbers (float or
integer dtypes, converted to float64); another dtype raises ``TypeError``, another shape or an
empty array ``ValueError``. Arrays out are ``numpy.ndarray`` of float64.
"""

from os import PathLike
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union, final

import numpy as np
import numpy.typing as npt

__all__ = ["Board", "BoardError", "Params", "identify", "load_params", "settings_schema"]

_ArrayLike = Union[npt.ArrayLike, Sequence[float]]
_Signals = Union[str, Sequence[str]]

class BoardError(Exception):
    """A request the board refused (its NACK), or a parameter load refused before sending.

    Nothing was applied. The attributes say what was refused and why.
    """

    request: str
    """The request refused (``"LoadParams"``, ``"Capture"``, ``"Waveform"``, ...)."""
    field: Optional[str]
    """The setting or request field refused (``"drive.bias"``, ``"record count"``,
    ``"ranges.input"``), or ``None`` for a refusal of the request as a whole (busy, no
    storage)."""
    reason: str
    """Why, in words (``"must be at most 140"``)."""
    rule: Optional[str]
    """The rule broken (``"AtMost"``, ``"NotFinite"``, ``"TooMany"``, ...), or ``None``."""
    limit: Optional[float]
    """The rule's limit in the field's units (``140.0``), where it has one."""
    accepted: int
    """(A refused stream only.) Setpoints the board accepted before the refusal."""

@final
class Params:
    """An identified model and its parameter file: what ``twinstack identify`` writes and
    ``twinstack load`` sends. Made by :func:`identify`, :func:`load_params` or
    :meth:`Params.from_json`."""

    def predict(
        self, u: _ArrayLike, t: Optional[_ArrayLike] = None, rate: Optional[float] = None
    ) -> np.ndarray:
        """The model's predicted sensor reading (output unit) for the drive ``u`` (volts),
        run in the board's fixed point from rest at ``u[0]``.

        ``t`` (seconds, strictly increasing) or ``rate`` (samples per second) gives the sample
        period a creep operator and a sensor lag run at; a model with neither needs neither.
        """
    def compensate(
        self,
        x: _ArrayLike,
        t: Optional[_ArrayLike] = None,
        rate: Optional[float] = None,
        measured: bool = False,
        resonance: Optional[Tuple[float, float]] = None,
    ) -> np.ndarray:
        """The drive (volts) the board's compensator gives for the desired reading ``x``
        (output unit), in its fixed point; ``t``/``rate`` as in :meth:`predict`. Every sample
        is inverted exactly, as the board inverts its setpoints; with ``measured=True`` ``x``
        is a sensor's record, followed through its noise band (Duhem, Bouc–Wen) as
        ``twinstack identify`` scores an inverse. With ``resonance=(hz, damping)`` (what
        ``twinstack tune`` fits) the planned ``x`` is shaped first so that the stage's
        resonance does not ring at its corners, as ``twinstack compensate --resonance-hz``
        does: it needs ``t`` (evenly spaced) or ``rate``, and not ``measured``."""
    def save(self, path: Union[str, "PathLike[str]"]) -> None:
        """Writes the parameter file (the same JSON ``twinstack identify`` writes)."""
    def to_json(self) -> str:
        """The parameter file's JSON text."""
    @staticmethod
    def from_json(text: str) -> "Params":
        """A parameter file's JSON text, checked as :func:`load_params` checks a file
        (``ValueError`` naming the field otherwise)."""
    @property
    def model(self) -> str:
        """The hysteresis model: ``"pi"``, ``"duhem"``, ``"gpi"`` or ``"bouc-wen"``."""
    @property
    def creep(self) -> bool:
        """Whether a creep operator runs in series with the model."""
    @property
    def output_map(self) -> bool:
        """Whether a static output map follows the model (a Bouc-Wen's, fitted with
        ``identify(..., output_map=True)``)."""
    @property
    def input_range(self) -> Tuple[float, float]:
        """The model's input range, volts."""
    @property
    def output_range(self) -> Tuple[float, float]:
        """The model's (sign-corrected) output range, in :attr:`output_unit`."""
    @property
    def output_sign(self) -> float:
        """``1.0``, or ``-1.0`` when the sensor reads the model's output negated."""
    @property
    def sensor_lag_s(self) -> float:
        """The sensor's lag behind the drive, seconds."""
    @property
    def fastest_motion_hz(self) -> Optional[float]:
        """The fastest motion the model was fitted on, Hz: the highest rate at which the
        fitted part's drive swings by a fifth of its span or more; ``None`` where the file
        does not say. A model holds at the rates it was fitted on: for faster motion,
        calibrate with ``Board.calibrate(fastest_hz=...)``."""
    @property
    def resonance(self) -> Optional[Tuple[float, float]]:
        """The stage's resonance as ``calibrate`` measured it, ``(frequency_hz, damping)``,
        or ``None``: pass it as ``resonance=`` to :meth:`compensate` or :meth:`Board.stream`
        to shape a planned trajectory for it."""
    @property
    def output_unit(self) -> str:
        """The unit of the model's output (the identified record's ``x``)."""
    @property
    def settings(self) -> Dict[str, Any]:
        """The board settings the file carries (its ``settings`` object) as a dict."""
    @property
    def identification(self) -> Optional[Dict[str, Any]]:
        """How the model was fitted and scored (the file's ``identification``): fit and
        held-out error figures, lag, notes; ``None`` for a file without it."""
    @property
    def ranking(self) -> Optional[List[Dict[str, Any]]]:
        """``model="auto"``'s ranking, best first, by what the stage will see: dicts with
        ``label``; on the validation part the forward fit's ``max_pct`` / ``rms_pct``, the
        compensator's ``inverse_max_pct`` / ``inverse_rms_pct`` and ``tracking_max_pct`` /
        ``tracking_rms_pct``, ``compensated_pct`` (the larger max: the ranking's key) and
        ``set_aside`` (why a ratcheting inverse was ranked last); ``not_admitted``, the reason,
        for a model the board would not run at ``tick_rate``; or ``error``. ``None``
        otherwise."""

def identify(
    t: _ArrayLike,
    u: _ArrayLike,
    x: _ArrayLike,
    model: str = "auto",
    creep: Optional[bool] = None,
    fit_until: Optional[float] = None,
    operators: Optional[int] = None,
    thresholds: str = "uniform",
    lag: Optional[float] = None,
    output_unit: str = "um",
    tick_rate: Optional[float] = None,
    observer: bool = True,
    output_map: bool = False,
    fastest_hz: Optional[float] = None,
) -> Params:
    """Identifies a hysteresis model from a measured record: ``t`` seconds (strictly
    increasing), ``u`` the drive in volts, ``x`` the measured output.

    Samples with ``t < fit_until`` are fitted, the rest held out to score the model
    (default: the first 70 % of the record's duration). ``model``: ``"auto"`` fits every
    model (P-I, Duhem, generalised P-I, Bouc-Wen) on the first part of the fit window, ranks
    them on its last part and keeps the best, as ``twinstack identify`` does; or one of
    ``"pi"``, ``"duhem"``, ``"gpi"``, ``"bouc-wen"``. ``creep``: ``None`` lets ``auto`` try
    each model with and without a creep operator (one model: without), ``True`` fits one,
    ``False`` none. ``operators``/``thresholds``: the P-I's play operators (1 to 32; ``None``:
    17, or fewer where ``tick_rate`` needs it) and their spread (``"uniform"`` or
    ``"geometric"``); ``lag``: the sensor lag in samples, a whole or a half number
    (``1.5``: a reading of a held drive's end; estimated in half samples when ``None``). ``tick_rate`` (Hz): keep only a model the board runs at that control rate
    (its tick budget, as the board applies it at load), made smaller where that makes it fit
    (creep with fewer modes; fewer play operators unless ``operators`` is given); ``auto``
    picks among those, a model asked for by name that does not fit raises ``ValueError``.
    ``observer=False``: the file runs the model as the compensator only (no estimate, no drift
    check on the board, and the observer's cost off its tick, so larger models fit a fast
    board, as ``twinstack identify --no-observer``). ``output_map=True``: a static output map
    (four dead zones a side) is fitted after the Bouc-Wen model, the model refined with it,
    and kept only where it lowers the fit error (``twinstack identify --output-map``); with
    ``"auto"`` only the Bouc-Wen candidates with a map are ranked (without it, ``auto`` ranks
    Bouc-Wen with and without one); another model raises ``ValueError``. ``fastest_hz``: the
    fastest motion the model will run, Hz; where the fitted part's own
    (:attr:`Params.fastest_motion_hz`) is more than an octave slower, a ``UserWarning`` says
    so and how to record one that reaches it, as ``twinstack identify --fastest-hz`` does
    (the model is still returned). Runs without the interpreter's lock. ``ValueError`` says
    why a record cannot be fitted."""

def settings_schema() -> List[Tuple[str, str]]:
    """Every settings path with what it holds, as ``(path, kind)`` pairs (``twinstack settings
    --schema``)."""

def load_params(path: Union[str, "PathLike[str]"]) -> Params:
    """Reads and checks a parameter file (``twinstack identify``'s, or :meth:`Params.save`'s);
    ``ValueError`` names the field refused, ``FileNotFoundError`` a missing file."""

@final
class Board:
    """A twinstack board.

    ``port``: a serial device (``"/dev/ttyUSB0"``, ``"COM3"``, a pty), ``"tcp:HOST:PORT"``
    (``twinstack virtual-board``, QEMU's UART), ``"unix:PATH"``, or ``"sim"``: a simulated board
    in-process, fresh at each ``Board("sim")``, whose time runs only while a call waits on it.
    ``baud`` sets a serial device's rate; ``timeout`` (seconds) how long each request waits
    for its response.

    Every call that waits on the board lets go of the interpreter's lock. A refusal raises
    :class:`BoardError`; no answer ``TimeoutError``; a broken link ``ConnectionError``. Use it
    as a context manager, or call :meth:`close`.
    """

    def __new__(
        cls,
        port: str,
        baud: int = 3000000,
        timeout: float = 2.0,
        sim_camera_hz: Optional[float] = None,
        sim_camera_frames: int = 0,
        sim_camera_on_settled: bool = False,
    ) -> "Board":
        """Opens ``port`` and cleans the line. With ``port="sim"``, ``sim_camera_hz`` puts a
        simulated camera on the board's trigger input: ``sim_camera_frames`` frames (0: until
        the sequence is disarmed) from each arming of a sequence (or of a scan or the stream
        on the input's edge, until it starts), free-running or, with
        ``sim_camera_on_settled``, each started by the settled output."""
    @property
    def port(self) -> str:
        """The port this board was opened on."""
    def status(self) -> Dict[str, Any]:
        """Status and telemetry: ``image`` (board/emulator/simulator), ``ticks``,
        ``tick_rate_hz``, ``mode``, ``flags`` (streaming, waveform, recording, defaults),
        queue and link counters, ``limit_hits``, ``drifts`` (ticks the drift check flagged
        since start-up), ``estimate`` (normalised), ``recorded``."""
    def load(
        self,
        params: Params,
        clamp: bool = False,
        mode: Optional[str] = None,
        store: Optional[str] = None,
        preview: Optional[bool] = None,
    ) -> None:
        """Loads the settings of ``params`` (validated whole by the board, prepared off the
        control tick and swapped in with the drive continuous); the sensor calibration,
        feedback gains, input shaping and preview the file leaves out are kept from the board.

        ``preview=True`` runs the preview on the board for the resonance ``params`` holds
        (``params.resonance``, what ``calibrate`` measured; ``ValueError`` where it holds
        none): every setpoint shaped for the resonance before the compensator, the feedback
        aiming at the setpoint itself, the stage following the trajectory four ticks late.
        ``preview=False`` turns the board's off; ``None`` keeps the file's or the board's.

        ``mode`` (``"bypass"``, ``"open-loop"``, ``"closed-loop"``) overrides the file's;
        ``store`` also writes the settings to flash, to boot in that mode. A model whose input
        range the drive cannot reach raises :class:`BoardError` (``field="ranges.input"``)
        unless ``clamp=True``, which loads it with a ``RuntimeWarning``."""
    def params(self) -> Dict[str, Any]:
        """The settings in force on the board, physical units (a parameter file's
        ``settings``)."""
    def get(self, path: str) -> Any:
        """One setting by its path (``"/feedback/kp"``; :func:`settings_schema` lists them),
        as the Python value of its JSON (``None`` for a part that is not set); ``KeyError``
        names a path that names nothing."""
    def set(self, path: str, value: Any) -> Any:
        """Changes one setting by its path and loads the settings whole (validated by the
        board, swapped in bumplessly); returns the value the board then holds. ``KeyError``:
        a path that names nothing; ``ValueError``: a value of the wrong type;
        ``BoardError``: the board's refusal (field and limit)."""
    def mode(self, mode: str) -> None:
        """Switches to ``"bypass"``, ``"open-loop"`` or ``"closed-loop"`` (bumpless)."""
    def stream(
        self,
        setpoints: _ArrayLike,
        rate: Optional[float] = None,
        normalised: bool = False,
        underrun: Optional[str] = None,
        wait: bool = True,
        resonance: Optional[Tuple[float, float]] = None,
        more: bool = False,
        start_on: str = "now",
        edge_timeout: float = 60.0,
    ) -> Dict[str, Any]:
        """Streams ``setpoints`` to the board: in the output unit of the settings in force
        (or -1...1 with ``normalised=True``; a value outside the range raises ``ValueError``,
        nothing is sent), ``rate`` setpoints per second (the tick rate divided by a whole
        number; default: one per tick), within the credits the board grants. Starts the
        stream once the queue is primed and, with ``wait``, waits until it has played and
        stops it. ``underrun``: ``"hold"`` or ``"ramp-to-bias"`` when the queue runs dry.
        ``resonance=(hz, damping)`` (what ``twinstack tune`` fits) shapes the setpoints first
        so that the stage's resonance does not ring at their corners, as ``twinstack stream
        --resonance-hz`` does: for a board in open or closed loop, one setpoint a tick (else
        ``ValueError``, nothing sent). ``more=True``: more setpoints follow in the next call
        (with ``wait=False``): the stream plays on without its end, and the next ``stream``
        queues its setpoints behind these instead of stopping them, so the parts play as one
        stream. ``start_on="rising"`` or ``"falling"``: the queue is primed and the trigger
        input armed, and the stream starts on that edge (a camera's frame), waited for at most
        ``edge_timeout`` seconds (then ``TimeoutError``: the input is disarmed and the setpoints
        accepted stay queued).

        Ctrl-C stops the stream, tells the board to stop, and raises ``KeyboardInterrupt``.
        Returns a report: ``accepted``, ``divider``, ``batches``, ``underruns`` (``None`` when
        they cannot be ruled out), ``underran``, ``seconds`` and link counters."""
    def shaped(
        self,
        setpoints: _ArrayLike,
        resonance: Optional[Tuple[float, float]],
        rate: Optional[float] = None,
        normalised: bool = False,
    ) -> np.ndarray:
        """The setpoints :meth:`stream` would send for these arguments, normalised (-1...1, the
        board's Q1.15 values): with ``resonance``, shaped for the stage's resonance as
        ``stream`` shapes them. Nothing is sent; refused (``ValueError``) as ``stream`` refuses
        them."""
    def sequence(
        self,
        positions: _ArrayLike,
        window: float = 0.005,
        settle_ticks: int = 25,
        edge: str = "rising",
        normalised: bool = False,
        mode: Optional[str] = None,
        idle: float = 5.0,
    ) -> Dict[str, Any]:
        """Runs a TTL-stepped sequence: ``positions`` (in the output unit of the settings in
        force, or -1...1 with ``normalised=True``; a value outside the range raises
        ``ValueError``, nothing is sent) go through the setpoint queue, topped up as the edges
        on the trigger input (``edge``: ``"rising"`` or ``"falling"``) consume them, one per
        edge; the settled output goes high once the stage has stayed within ``window``
        (normalised) for ``settle_ticks`` ticks. ``mode`` switches the mode first. Ends when
        every position is reached or no edge came for ``idle`` seconds, then disarms.
        Returns ``positions``, ``sent``, ``steps``, ``early`` (edges before the stage had
        settled), ``missed`` (edges with no position left), ``complete`` and
        ``ticks_to_motion`` (the first edge's tick to its first moved DAC sample)."""
    def analog(
        self,
        gain: float = 2.0,
        offset: float = ...,
        corner_hz: Optional[float] = None,
        lost_below: float = 0.0,
        over_above: float = 1.0,
        on_fault: str = "hold",
        rate: float = 10.0,
    ) -> None:
        """Makes the board's analog setpoint input the setpoint source: the input's span
        (0 V to 3.3 V at the pin) times ``gain`` plus ``offset`` (default -1.0), normalised
        displacement; low-pass filtered at ``corner_hz`` (``None``: unfiltered); below ``lost_below`` or
        above ``over_above`` (fractions of the span) the input is faulty and the output holds
        (``on_fault="hold"``) or ramps to rest (``"ramp-to-rest"``) at ``rate`` (normalised
        per second, also the rate it walks back at). Refused settings raise ``ValueError``
        naming the field, nothing sent; a board busy with another source raises."""
    def analog_status(self) -> Dict[str, Any]:
        """The analog input's state: ``running``, ``lost``, ``over_range``, ``faults``,
        ``reading`` (fraction of the span) and ``setpoint`` (normalised)."""
    def stop(self) -> None:
        """Stops the setpoint stream, the waveform or the analog input; the output holds
        where it is."""
    def waveform(
        self, amplitude: float, frequency: float, shape: str = "sine", offset: float = 0.0
    ) -> None:
        """Starts the board's waveform generator: ``"sine"`` or ``"triangle"``, ``offset`` and
        ``amplitude`` normalised (``offset +- amplitude`` within -1...1), ``frequency`` in Hz
        (resolution 1 mHz). :meth:`stop` stops it."""
    def arm(
        self,
        signals: _Signals,
        samples: int,
        trigger: str = "now",
        pre: int = 0,
        decimation: int = 1,
    ) -> None:
        """Arms a multi-signal capture and returns at once; :meth:`fetch` reads it. For a
        capture triggered by this connection's own :meth:`stream` (``trigger="stream"``) or
        :meth:`waveform` (``"waveform"``). Arguments as for :meth:`record`."""
    def fetch(self, timeout: float = 30.0) -> Dict[str, np.ndarray]:
        """Waits (at most ``timeout`` seconds, ``TimeoutError`` after) for the capture armed
        before, and reads it back as :meth:`record` returns it."""
    def record(
        self,
        signals: _Signals,
        samples: int,
        trigger: str = "now",
        pre: int = 0,
        decimation: int = 1,
        timeout: float = 30.0,
    ) -> Dict[str, np.ndarray]:
        """Records ``signals`` (any of ``"setpoint"``, ``"left"``, ``"right"``, ``"sensor"``,
        ``"estimate"``, ``"error"``; a list or one comma-separated string) at once:
        ``samples`` frames, ``pre`` of them from before the trigger (``"now"``, ``"stream"``,
        ``"waveform"``), one every ``decimation`` ticks; waits for it (at most ``timeout``
        seconds) and reads it back.

        Returns a dict of float64 arrays in physical units: ``"t"`` seconds from the trigger
        (negative before it), the stacks ``"left"``/``"right"`` in volts, the displacements
        (setpoint, sensor, estimate, error) in the output unit of the settings in force. A
        request beyond the board's buffer raises :class:`BoardError` with its ``limit``."""
    def coarse_home(self, wait: bool = True, timeout: float = 120.0) -> Dict[str, Any]:
        """Homes the dual-actuated stage's coarse axis; with ``wait``, its status once the
        homing has ended (``RuntimeError`` naming the faults if it did not home)."""
    def coarse_move(
        self,
        to_mm: float,
        speed: float = 10.0,
        accel: float = 200.0,
        wait: bool = True,
        timeout: float = 120.0,
    ) -> Dict[str, Any]:
        """Moves the coarse axis to ``to_mm`` (a homed axis); with ``wait``, its status once
        the move has ended. The board's refusal raises :class:`BoardError`."""
    def coarse_jog(self, speed: float) -> None:
        """Jogs the coarse axis at ``speed`` mm/s until :meth:`coarse_stop`."""
    def coarse_stop(self) -> None:
        """Stops the coarse axis (it brakes; still homed)."""
    def coarse_release(self) -> None:
        """Hands the piezo back from the coarse axis (at rest) to its own sources (stream,
        waveform, scans, sequences, the analog input) while the carriage holds; the next
        coarse home, move or jog takes it again (:class:`BoardError` busy while one of those
        sources runs)."""
    def coarse_status(self) -> Dict[str, Any]:
        """``state``, ``homed``, ``position_mm``, ``setpoint_mm``, ``following_error_um``,
        ``faults``, ``switches``, ``fine_setpoint``, ``ticks``, and ``piezo``: ``"coarse"``
        while the piezo follows the coarse axis, ``"own"`` once released."""
    def learn(
        self,
        period_ticks: int,
        gain: float = 0.3,
        cutoff_hz: float = 3000.0,
        lead_ticks: int = 1,
        limit: float = 0.25,
        reset: bool = True,
    ) -> None:
        """Starts the board's learning feedforward for a periodic motion of ``period_ticks``
        ticks (2 … 512, a whole number of the motion's cycles): it learns, period by period,
        the correction that takes its sensor's error out of the motion. ``reset`` empties the
        table first. Settings checked first (``ValueError`` naming the ``learning.*`` field,
        nothing sent)."""
    def learn_state(self, state: str) -> None:
        """``"learning"``, ``"frozen"`` (the table plays as it is) or ``"off"``."""
    def learn_status(self) -> Dict[str, Any]:
        """``state``, ``period_ticks``, ``periods``, ``updates``, ``missed`` and the last
        period's ``error_max`` / ``error_rms`` in the output unit."""
    def learn_table(self) -> np.ndarray:
        """The table playing now: one normalised correction a tick of the period."""
    def learn_load_table(self, table: _ArrayLike) -> None:
        """Plays ``table`` (as :meth:`learn_table` returns it) from the next period boundary,
        in the learning's state; another length or a value not finite within ±2 raises
        ``ValueError``, nothing sent."""
    def scan(
        self,
        pattern: str,
        ticks_per_pixel: int = 4,
        frames: int = 1,
        pulse: int = 2,
        timeout: float = 60.0,
        start_on: str = "now",
    ) -> Dict[str, Any]:
        """Runs a scan pattern generated on the board (as ``twinstack scan``) with its pixel,
        line and frame trigger outputs (pulses of ``pulse`` ticks) and reads it back:
        ``pattern`` as ``twinstack scan --pattern`` takes it (``"raster:lines=64,pixels=64"``,
        ``"lissajous:hz=20,x=3,y=2"``, ``"spiral:hz=200,turns=10"``), ``frames`` (0: endless,
        stopped once the capture is read). Returns ``"t"`` (seconds from the scan's start),
        ``"setpoint"`` (output unit), ``"y"`` (the replay's slow axis, normalised; NaN during
        the approach), ``"pixel"``, ``"line"``, ``"frame"`` (bool arrays of the outputs'
        levels), ``"figures"`` (the clocks against the library's replay, as ``twinstack scan
        --json``), ``"truncated"`` and ``"kind"`` (the pattern parsed: ``"raster"``,
        ``"lissajous"`` or ``"spiral"``). ``start_on`` ``"rising"`` or ``"falling"``: the scan waits
        for that edge of the trigger input (a camera's frame starts it). A pattern the board
        would refuse raises ``ValueError`` naming the field (nothing sent); a scan that differs
        from the replay ``RuntimeError``."""
    def telemetry(
        self,
        signals: _Signals,
        rate: float = 10000.0,
        seconds: float = 1.0,
    ) -> Dict[str, Any]:
        """Continuous telemetry: the board sends ``signals`` (as :meth:`record`'s) at the rate
        nearest ``rate`` samples per second (the tick rate divided by a whole number) while it
        runs whatever it runs, for ``seconds`` of samples; then telemetry stops and its end
        frame is awaited. Returns float64 arrays in physical units, ``"t"`` (seconds from the
        first sample; a gap shows as a jump) and one per signal, with ``"rate_hz"``,
        ``"decimation"``, ``"samples"`` (received), ``"missing"`` (taken, not received),
        ``"lost_on_board"`` (of them, dropped on the board, its queue full),
        ``"frames_damaged"`` and ``"complete"``. Anything missing also raises a
        ``RuntimeWarning``. A rate the board's link cannot carry for that many signals raises
        :class:`BoardError` naming the most it can; a rate beyond the tick rate, or
        ``seconds`` not positive, ``ValueError``."""
    def calibrate(
        self,
        store: bool = True,
        clamp: bool = False,
        model: Optional[str] = None,
        resonance: bool = True,
        fastest_hz: Optional[float] = None,
    ) -> Dict[str, Any]:
        """One-command calibration (``twinstack calibrate``): excites the stage with the
        identification excitation streamed in bypass (full-range cycles, decaying minor loops,
        nested off-centre loops, a multisine), records drive and sensor, identifies the best model of the family
        (or ``model``), loads it, tracks a test trajectory before (bypass) and after (open
        loop), and stores it unless ``store`` is false. Returns ``params`` (a
        :class:`Params`), ``model``, ``reason``, ``held_out`` / ``before`` / ``after``
        (``max_pct``, ``rms_pct``), ``stored``, ``clamped``, ``excitation_underran`` (the
        excitation's stream found the queue empty: identified on the drive as applied),
        ``resonance`` (the stage's resonance measured after the excitation as ``tune``
        measures it, ``(frequency_hz, damping)``, also ``params.resonance``; ``None`` with
        ``resonance=False`` or where none fitted, then ``resonance_not_fitted`` says why).
        ``fastest_hz`` names the fastest motion the stage will run (``calibrate
        --fastest-hz``): the excitation sweeps up to it before its multisine, and one the board
        would not stream and record with 20 samples a cycle raises ``RuntimeError`` naming
        ``fastest_hz`` before anything moves. Board refusals raise
        :class:`BoardError`; a stage that cannot be calibrated raises ``RuntimeError``."""
    def tune(
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
        """Tunes the feedback in one call (``twinstack tune``): measures the stage's frequency
        response with the board's generator and recorder (in bypass; the mode is restored),
        fits its resonance and the loop's delay, and designs the PI gains and the notch for at
        least ``phase_margin`` degrees and ``gain_margin`` dB (also with the fit's gain 1.4
        times higher, and at most 0.5 % ringing of a step on the model). With ``kp`` and
        ``ki`` (and ``notch_hz``, ``notch_q``, ``notch_depth``, ``limit``) it checks that gain
        set instead. ``load`` loads the result, the other settings kept.

        Returns what ``twinstack tune --json`` prints: ``rate_hz``, ``points``
        (``frequency_hz``, ``magnitude_db``, ``phase_deg``), ``fit`` (``gain``,
        ``resonance_hz``, ``zeta``, ``delay_ticks``, ``rms_db``, ``rms_deg``), ``goals``,
        ``feedback`` (the settings chosen or checked, as :meth:`params`' ``feedback``),
        ``figures`` (``phase_margin_deg``, ``gain_margin_db``, ``closed_loop_bandwidth_hz``,
        ``bandwidth_hz``, ``ringing_pct``, ... on the fit), ``shaping`` (the input shaping for
        the resonance), ``before`` (the board's gains before and their verdict), ``loaded``
        and ``board_timing``.

        Margins not finite or negative, ``kp`` without ``ki`` (or the reverse), ``notch_hz``
        without them, or a gain set the board would refuse at its rate raise ``ValueError``
        naming it, before anything moves; a checked set the fitted model says is unstable or
        short of the margins ``ValueError`` (nothing loaded); no gains that meet the margins,
        or a response that does not fit, ``RuntimeError``; the board's refusals
        :class:`BoardError`; a ``progress`` that is not callable ``TypeError``.

        ``progress`` is called with each point as it is measured (the coarse sweep, then the
        points about the resonance) as a dict: ``frequency_hz``, ``magnitude_db``,
        ``phase_deg`` (as in ``points``), ``drive_volts`` (the drive's amplitude, left-stack
        volts) and ``sensor_amplitude`` (the sensor's, output unit). An exception it raises
        stops the sweep and goes up; Ctrl-C stops it too (``KeyboardInterrupt``). After a stop
        the generator is stopped, the board's mode restored and nothing loaded."""
    def store(self, boot_mode: str = "bypass") -> None:
        """Writes the settings in force to the board's flash, to boot in ``boot_mode``."""
    def recall(self) -> None:
        """Reloads the settings stored in flash (:class:`BoardError` when none are)."""
    def close(self) -> None:
        """Closes the link; a ``"sim"`` board is gone with it. Later calls raise
        ``RuntimeError``."""
    def __enter__(self) -> "Board":
        """The board itself."""
    def __exit__(self, *args: object) -> bool:
        """Closes the board."""
