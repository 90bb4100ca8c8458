"""The lab workflow from Python: identify a model from a measured record, compensate a
trajectory with it, then on a (virtual) board identify its own stage from a recording, load
the model, stream a trajectory, record what the stage did, and plot it all to a PNG.

    python python/examples/workflow.py [--port PORT] [--out workflow.png]

PORT is the board: a serial device, tcp:HOST:PORT (a running `twinstack virtual-board`), or
`sim` (the simulated board in-process). Without --port the example starts a virtual board
itself (`twinstack virtual-board --listen tcp:127.0.0.1:0`, the binary from --hal-sim,
$TWINSTACK_HAL_SIM or the PATH) and stops it at the end.
"""

import argparse
import os
import pathlib
import shutil
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import twinstack  # noqa: E402

REPO = pathlib.Path(__file__).resolve().parents[2]
DATA = REPO / "data" / "micromanipulator-unipolar-3v6-1hz.csv"


def read_record(path):
    """t, u, x of one of the repository's CSV records (`#` comments, then a t,u,x header)."""
    comments = sum(1 for line in open(path) if line.startswith("#"))
    t, u, x = np.loadtxt(path, delimiter=",", skiprows=comments + 1).T
    return t, u, x


def start_virtual_board(hal_sim):
    """A `twinstack virtual-board` process on a free port: (process, port)."""
    proc = subprocess.Popen(
        [hal_sim, "virtual-board", "--listen", "tcp:127.0.0.1:0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    words = proc.stdout.readline().split()
    if "listening" not in words:
        proc.kill()
        sys.exit("the virtual board did not start")
    return proc, words[words.index("on") + 1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", help="the board (default: start a virtual board)")
    ap.add_argument("--hal-sim", default=os.environ.get("TWINSTACK_HAL_SIM") or shutil.which("twinstack"))
    ap.add_argument("--out", default="workflow.png")
    args = ap.parse_args()

    # 1. Identify: every model ranked on data it was not fitted on, the best kept.
    t, u, x = read_record(DATA)
    params = twinstack.identify(t, u, x, fit_until=16.0, output_unit="sensor units")
    held = params.identification["held_out"]
    print(f"identified {params.model} (creep: {params.creep}) from {DATA.name}:")
    for r in params.ranking:
        print(f"  {r['label']:<50} validation max {r.get('max_pct', float('nan')):.2f} %")
    print(f"  held-out error: max {held['max_pct']:.2f} %, RMS {held['rms_pct']:.2f} % of span")
    predicted = params.predict(u, t=t)

    # 2. Compensate a trajectory: a decaying 0.5 Hz sine over the model's output range,
    # sampled as the record is (200 Hz); the model run on the compensator's drive should
    # give the trajectory back.
    rate = 1.0 / np.median(np.diff(t))
    tt = np.arange(int(10 * rate)) / rate
    lo, hi = params.output_range
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    desired = mid + 0.8 * half * np.exp(-tt / 8) * np.sin(2 * np.pi * 0.5 * tt)
    drive = params.compensate(desired, rate=rate)
    achieved = params.predict(drive, rate=rate)
    model_err = 100 * np.max(np.abs(achieved[20:] - desired[20:])) / np.ptp(desired)
    print(f"compensated trajectory through the model: max error {model_err:.2f} % of span")

    # 3. A board. The CSV's stage is not the board's, so the board's own model is identified
    # the same way, from a recording of its drive and sensor (in bypass, the drive follows the
    # setpoint), loaded, and a trajectory in µm is streamed and recorded: with the compensator
    # alone (open loop), then with sensor feedback (closed loop).
    proc = None
    port = args.port
    if port is None:
        if not args.hal_sim:
            sys.exit("no --port and no twinstack binary (--hal-sim, $TWINSTACK_HAL_SIM, PATH)")
        proc, port = start_virtual_board(args.hal_sim)
    runs = {}
    try:
        with twinstack.Board(port) as board:
            status = board.status()
            tick = status["tick_rate_hz"]
            print(f"board on {port}: {status['image']}, {tick} Hz, mode {status['mode']}")
            board.mode("bypass")
            n, divider = 10000, 10  # 2 s at 5 000 setpoints/s
            ts = np.arange(n) * divider / tick
            excite = 0.9 * np.exp(-ts / 1.0) * np.sin(2 * np.pi * 5.0 * ts)
            board.arm(["left", "sensor"], samples=n * divider // 10, trigger="stream", decimation=10)
            board.stream(excite, rate=tick / divider, normalised=True)
            cal = board.fetch()
            stage = twinstack.identify(cal["t"], cal["left"], cal["sensor"])
            held = stage.identification["held_out"]
            print(f"the board's stage: {stage.model}, held-out max {held['max_pct']:.2f} % of span")
            board.load(stage)
            n, divider = 2000, 10  # 0.4 s
            ts = np.arange(n) * divider / tick
            lo, hi = stage.output_range
            setpoints = (lo + hi) / 2 + 0.35 * (hi - lo) * np.exp(-ts / 0.3) * np.sin(2 * np.pi * 10.0 * ts)
            for mode in ("open-loop", "closed-loop"):
                board.mode(mode)
                board.arm(["setpoint", "left", "sensor", "estimate"], samples=n * divider // 5,
                          trigger="stream", decimation=5)
                report = board.stream(setpoints, rate=tick / divider)
                run = runs[mode] = board.fetch()
                err = np.max(np.abs(run["sensor"] - run["setpoint"]))
                print(f"{mode}: streamed {report['accepted']} setpoints (underruns "
                      f"{report['underruns']}), recorded {len(run['t'])} frames: tracking error "
                      f"max {err:.3f} um ({100 * err / np.ptp(run['setpoint']):.2f} % of span)")
            board.mode("bypass")
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()

    # 4. The figure.
    fig, ax = plt.subplots(3, 1, figsize=(9, 10))
    ax[0].plot(t, x, lw=0.8, label="measured")
    ax[0].plot(t, predicted, lw=0.8, label=f"{params.model} model")
    ax[0].axvline(16.0, color="grey", ls="--", lw=0.8, label="held out from here")
    ax[0].set(title=f"Identification ({DATA.name})", xlabel="t [s]", ylabel="x [sensor units]")
    ax[0].legend(fontsize=8)
    ax[1].plot(tt, desired, lw=0.8, label="desired")
    ax[1].plot(tt, achieved, lw=0.8, ls="--", label="model on the compensated drive")
    ax[1].set(title="Compensated trajectory (through the identified model)", xlabel="t [s]",
              ylabel="x [sensor units]")
    ax[1].legend(fontsize=8)
    run = runs["open-loop"]
    ax[2].plot(run["t"], run["setpoint"], lw=0.8, label="setpoint")
    for mode, r in runs.items():
        ax[2].plot(r["t"], r["sensor"], lw=0.8, label=f"sensor, {mode}")
    ax[2].plot(run["t"], run["estimate"], lw=0.8, ls=":", label="estimate (observer), open loop")
    ax[2].set(title=f"Streamed and recorded on the board ({port})",
              xlabel="t from the stream's start [s]", ylabel="displacement [um]")
    ax[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
