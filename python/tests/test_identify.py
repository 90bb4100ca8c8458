"""Identification from Python, and the parameter file's round trip with the `twinstack` CLI."""

import json
import subprocess
import warnings

import numpy as np
import pytest

import twinstack
from conftest import REPO, param_json

MICRO = REPO / "data" / "micromanipulator-unipolar-3v6-1hz.csv"


def read_csv(path):
    """The repository's t,u,x records: `#` comments, a header, then numbers."""
    return np.loadtxt(path, delimiter=",", comments="#", skiprows=1 + sum(
        1 for line in open(path) if line.startswith("#")
    )).T


@pytest.fixture(scope="module")
def micro():
    t, u, x = read_csv(MICRO)
    return t, u, x


def run(hal_sim, *args):
    out = subprocess.run(
        [hal_sim, *map(str, args)], cwd=REPO, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def test_the_cli_and_python_identify_the_same_model_and_read_each_others_files(
    hal_sim, micro, tmp_path
):
    t, u, x = micro
    cli_file = tmp_path / "cli.json"
    run(hal_sim, "identify", "--model", "pi", "--data", MICRO, "--fit-until", 16,
        "--output-unit", "um", "--out", cli_file)
    from_cli = twinstack.load_params(cli_file)
    ours = twinstack.identify(t, u, x, model="pi", fit_until=16.0)
    # The same library on the same numbers: the same model, bit for bit (the file as the CLI
    # wrote it, read by Python's correctly rounded parser).
    a, b = json.loads(cli_file.read_text()), json.loads(ours.to_json())
    assert a["settings"] == b["settings"]
    assert from_cli.model == "pi" and from_cli.output_range == pytest.approx(ours.output_range)
    assert (a["output_sign"], a["sensor_lag_s"]) == (b["output_sign"], b["sensor_lag_s"])
    assert a["identification"]["held_out"] == b["identification"]["held_out"]
    assert b["identification"]["fit_until_s"] == 16.0
    assert ours.identification["held_out"]["max_pct"] < 3.0
    # Both record the motion the model was fitted on: the record's 1 Hz.
    assert from_cli.fastest_motion_hz == ours.fastest_motion_hz == pytest.approx(1.0, rel=0.05)
    # Named faster than an octave beyond it, the run warns (and still returns the model), as
    # the CLI notes; within an octave, it does not.
    with pytest.warns(UserWarning, match=r"calibrate --fastest-hz 200"):
        warned = twinstack.identify(t, u, x, model="pi", fit_until=16.0, fastest_hz=200.0)
    assert warned.to_json() == ours.to_json()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        twinstack.identify(t, u, x, model="pi", fit_until=16.0, fastest_hz=1.5)
    for bad in (0.0, -5.0, float("nan"), float("inf"), 1e9):
        with pytest.raises(ValueError, match="fastest_hz .*at most 5000 Hz"):
            twinstack.identify(t, u, x, model="pi", fit_until=16.0, fastest_hz=bad)
    # Python writes, the CLI reads and runs it: its prediction is Python's.
    py_file = tmp_path / "py.json"
    ours.save(py_file)
    assert json.loads(py_file.read_text()) == json.loads(ours.to_json())
    assert twinstack.load_params(py_file).model == "pi"
    pred = tmp_path / "pred.csv"
    run(hal_sim, "predict", "--params", py_file, "--data", MICRO, "--out", pred)
    _, _, cli_x = np.loadtxt(pred, delimiter=",", skiprows=1).T
    # serde_json's default float parser can read a parameter back one unit in the last place
    # off, so the CLI's run of the file may differ by as much in the fixed point: 1e-6 of span.
    span = np.ptp(x)
    assert np.max(np.abs(cli_x - ours.predict(u, t=t))) <= 1e-6 * span
    comp = tmp_path / "comp.csv"
    run(hal_sim, "compensate", "--params", py_file, "--data", MICRO, "--out", comp)
    _, cli_u, _ = np.loadtxt(comp, delimiter=",", skiprows=1).T
    assert np.max(np.abs(cli_u - ours.compensate(x, t=t))) <= 1e-6 * np.ptp(u)
    # And the CLI loads Python's file onto a board.
    assert "loaded" in run(hal_sim, "load", "--port", "sim", "--params", py_file)


def test_a_bad_file_is_refused_naming_the_field(tmp_path):
    with twinstack.Board("sim") as b:
        settings = b.params()
    text = json.loads(param_json(settings))
    text["settings"]["drive"]["bias"] = 200.0
    with pytest.raises(ValueError, match="field `settings.drive.bias`"):
        twinstack.Params.from_json(json.dumps(text))
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(text))
    with pytest.raises(ValueError, match="bad.json: field `settings.drive.bias`"):
        twinstack.load_params(path)
    with pytest.raises(FileNotFoundError):
        twinstack.load_params(tmp_path / "missing.json")


def test_a_known_model_is_recovered():
    # The simulated board's P-I (8 operators over 0...140 V) as the "stage".
    with twinstack.Board("sim") as b:
        truth = twinstack.Params.from_json(param_json(b.params()))
    t = np.arange(4000) * 1e-3
    u = 70.0 + 65.0 * (1.0 - 0.5 * t / t[-1]) * np.sin(2 * np.pi * 2.0 * t)
    x = truth.predict(u, t=t)
    p = twinstack.identify(t, u, x, model="pi", fit_until=2.8, lag=0)
    assert p.model == "pi" and not p.creep and p.ranking is None
    held = p.identification["held_out"]
    assert held["max_pct"] < 0.5, held
    # The inverse undoes the forward model on the record.
    back = p.predict(p.compensate(x, t=t), t=t)
    span = np.ptp(x)
    assert np.max(np.abs(back[10:] - x[10:])) < 0.02 * span


@pytest.fixture(scope="module")
def micro_auto(micro):
    """`auto` on the micromanipulator record: identified once for the tests that read it."""
    t, u, x = micro
    return twinstack.identify(t, u, x, fit_until=16.0)


def test_auto_ranks_every_model_and_creep_selects_the_candidates(micro, micro_auto):
    t, u, x = micro
    p = micro_auto
    labels = [r["label"] for r in p.ranking]
    # Every model without and with creep, and the Bouc-Wen with an output map, both ways.
    assert len(labels) == 10 and sum("+ creep" in l for l in labels) == 5
    assert sum("+ output map" in l for l in labels) == 2
    assert p.model == {"P-I": "pi", "Duhem": "duhem", "generalised": "gpi", "Bouc-Wen": "bouc-wen"}[
        labels[0].split(" (")[0].split(" +")[0].replace("generalised P-I", "generalised")
    ]
    only = twinstack.identify(t, u, x, fit_until=16.0, creep=True)
    assert all("+ creep" in r["label"] for r in only.ranking) and len(only.ranking) == 5
    # The record starts with the stage still settling from before it; the creep follows that
    # drift (identify keeps a creep only where it lowers the fit RMS, as it does here).
    assert only.creep
    none = twinstack.identify(t, u, x, fit_until=16.0, creep=False)
    assert not any("+ creep" in r["label"] for r in none.ranking) and len(none.ranking) == 5


def test_auto_ranks_by_what_the_compensator_does(micro_auto):
    p = micro_auto
    scored = [r for r in p.ranking if "error" not in r]
    for r in scored:
        # Each candidate carries its compensator's figures beside its fit, and the key is the
        # larger of the inverse's and the tracking's max.
        assert r["inverse_max_pct"] >= r["inverse_rms_pct"] > 0
        assert r["tracking_max_pct"] >= r["tracking_rms_pct"] > 0
        assert r["compensated_pct"] == max(r["inverse_max_pct"], r["tracking_max_pct"])
    # The pick heads the ranking: among the admitted candidates not set aside, none
    # compensates better by more than the parsimony margin (5 %: a simpler model that close wins).
    kept = [r for r in scored if "not_admitted" not in r and "set_aside" not in r]
    assert kept and kept[0] is scored[0]
    assert all(kept[0]["compensated_pct"] <= r["compensated_pct"] * 1.05 + 1e-9 for r in kept[1:])


def test_an_output_map_is_fitted_after_a_bouc_wen_only(micro):
    t, u, x = micro
    # With auto, only the Bouc-Wen candidates with a map are ranked (with and without creep).
    mapped = twinstack.identify(t, u, x, fit_until=16.0, output_map=True)
    labels = [r["label"] for r in mapped.ranking]
    assert len(labels) == 2 and all("+ output map" in l for l in labels), labels
    assert mapped.model == "bouc-wen"
    # The map is kept where it lowers the fit error (here it does), and the file carries it.
    assert mapped.output_map and mapped.settings["output_map"]["thresholds"]
    assert "output_map=" in repr(mapped)
    # The board runs a map after a Bouc-Wen only: another model is refused, naming the option.
    with pytest.raises(ValueError, match="output_map: .*Bouc-Wen"):
        twinstack.identify(t, u, x, model="pi", fit_until=16.0, output_map=True)
    plain = twinstack.identify(t, u, x, model="pi", fit_until=16.0)
    assert not plain.output_map and plain.settings["output_map"] is None


def test_tick_rate_keeps_a_model_the_board_runs(micro):
    t, u, x = micro
    fast = twinstack.identify(t, u, x, fit_until=16.0, tick_rate=100_000.0)
    # The kept one is admitted; a candidate left out for the rate says so, with its figures.
    assert "not_admitted" not in fast.ranking[0] and "max_pct" in fast.ranking[0]
    refused = [r for r in fast.ranking if "not_admitted" in r]
    assert all("100 kHz" in r["not_admitted"] and "max_pct" in r for r in refused)
    # A generalised P-I of 17 operators and 8 dead zones runs at 100 kHz at its size, its
    # observer left out (below the tick it costs the services' loop beside its bank); so do
    # 32 asked for (what 80 % of the period holds beside the dead zones); with creep beside
    # them they do not.
    gpi = twinstack.identify(t, u, x, model="gpi", fit_until=16.0, tick_rate=100_000.0)
    assert gpi.identification["operators"] == 17 and gpi.settings["observer"] is None
    assert gpi.settings["compensator"] is not None
    many = twinstack.identify(
        t, u, x, model="gpi", operators=32, fit_until=16.0, tick_rate=100_000.0
    )
    assert many.identification["operators"] == 32 and many.settings["observer"] is None
    with pytest.raises(ValueError, match="1344"):
        twinstack.identify(
            t, u, x, model="gpi", operators=32, creep=True, fit_until=16.0, tick_rate=100_000.0
        )
    # At 50 kHz the observer fits and stays.
    slow = twinstack.identify(t, u, x, model="gpi", fit_until=16.0, tick_rate=50_000.0)
    assert slow.settings["observer"] is not None
    # Asked for without it, the file has no observer at any rate.
    alone = twinstack.identify(
        t, u, x, model="gpi", operators=32, fit_until=16.0, tick_rate=50_000.0, observer=False
    )
    assert alone.model == "gpi" and alone.settings["observer"] is None
    pi = twinstack.identify(t, u, x, model="pi", fit_until=16.0, tick_rate=100_000.0)
    assert pi.identification["operators"] == 17
    with pytest.raises(ValueError, match="tick_rate"):
        twinstack.identify(t, u, x, fit_until=16.0, tick_rate=-1.0)


def test_a_given_lag_is_a_whole_or_half_number_of_samples(micro):
    t, u, x = micro
    with pytest.raises(ValueError, match="lag 0.3"):
        twinstack.identify(t, u, x, model="pi", fit_until=16.0, lag=0.3)
    p = twinstack.identify(t, u, x, model="pi", fit_until=16.0, lag=1.5)
    assert p.identification["lag_samples"] == 1.5
    assert p.sensor_lag_s == pytest.approx(1.5 * np.median(np.diff(t)))


def test_a_planned_trajectory_is_inverted_exactly_and_a_measured_one_through_its_band():
    # A Duhem model of the simulated board's stage, from a noisy record of it.
    with twinstack.Board("sim") as b:
        truth = twinstack.Params.from_json(param_json(b.params()))
    t = np.arange(4000) * 1e-3
    u = 70.0 + 65.0 * np.sin(2 * np.pi * 2.0 * t)
    x = truth.predict(u, t=t)
    noisy = x + 0.002 * np.ptp(x) * np.random.default_rng(1).standard_normal(x.size)
    duhem = twinstack.identify(t, u, noisy, model="duhem", fit_until=2.8, lag=0)
    # A planned trajectory at 20 samples a period gives its own drive back: no sample of it is
    # taken for noise, however far it moves from one to the next.
    tc = np.arange(400) * 5e-4
    uc = 70.0 + 60.0 * np.sin(2 * np.pi * 100.0 * tc)
    xc = duhem.predict(uc, t=tc)
    assert np.max(np.abs(duhem.compensate(xc, t=tc)[1:] - uc[1:])) < 1e-3 * 140.0
    # The noisy record, measured: through its band the drive stays nearer the one measured
    # than the exact inverse, which ratchets on the noise.
    exact = duhem.compensate(noisy, t=t)
    banded = duhem.compensate(noisy, t=t, measured=True)
    assert np.max(np.abs(banded[1000:] - u[1000:])) < np.max(np.abs(exact[1000:] - u[1000:]))


def test_a_planned_trajectory_shaped_for_the_resonance_as_the_cli_shapes_it(micro, tmp_path, hal_sim):
    # The micromanipulator's P–I; a 2 Hz triangle at 200 Hz; a resonance at 60 Hz.
    t, u, x = micro
    params = twinstack.identify(t, u, x, model="pi", fit_until=16.0)
    tc = np.arange(400) / 200.0
    phase = np.mod(2.0 * tc, 1.0)
    lo, hi = np.min(x), np.max(x)
    xc = lo + (hi - lo) * (0.3 + 0.4 * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase))
    plain = params.compensate(xc, t=tc)
    shaped = params.compensate(xc, t=tc, resonance=(60.0, 0.05))
    assert np.max(np.abs(shaped - plain)) > 0.01 * np.ptp(plain)
    # At the rate instead of the times: the same drive.
    assert np.array_equal(params.compensate(xc, rate=200.0, resonance=(60.0, 0.05)), shaped)
    # The command line's drive, from the same file and trajectory.
    params.save(tmp_path / "p.json")
    np.savetxt(tmp_path / "planned.csv", np.column_stack([tc, xc]), delimiter=",",
               header="t,x", comments="")
    run(hal_sim, "compensate", "--params", tmp_path / "p.json", "--data",
        tmp_path / "planned.csv", "--out", tmp_path / "drive.csv",
        "--resonance-hz", "60", "--resonance-damping", "0.05")
    _, cli, _ = read_csv(tmp_path / "drive.csv")
    assert np.max(np.abs(cli - shaped)) < 1e-6
    # A file holding the resonance (as `calibrate` writes it): `--preview` and
    # `params.resonance` shape for it, the same drive again.
    assert params.resonance is None
    text = json.loads(params.to_json())
    text["resonance"] = {"frequency_hz": 60.0, "damping": 0.05}
    measured = twinstack.Params.from_json(json.dumps(text))
    assert measured.resonance == (60.0, 0.05)
    assert np.array_equal(measured.compensate(xc, t=tc, resonance=measured.resonance), shaped)
    (tmp_path / "measured.json").write_text(json.dumps(text))
    run(hal_sim, "compensate", "--params", tmp_path / "measured.json", "--data",
        tmp_path / "planned.csv", "--out", tmp_path / "previewed.csv", "--preview")
    _, cli, _ = read_csv(tmp_path / "previewed.csv")
    assert np.max(np.abs(cli - shaped)) < 1e-6
    # What it cannot do is refused, naming it.
    for kwargs, message in [
        (dict(t=tc, resonance=(150.0, 0.05)), "below half the sample rate"),
        (dict(t=tc, resonance=(60.0, 1.5)), "damping ratio 1.5"),
        (dict(t=tc, resonance=(0.5, 0.05)), "outside the model's output range"),
        (dict(t=tc, resonance=(1e-300, 0.05)), "too slow to shape"),
        (dict(t=tc, resonance=(60.0, 0.05), measured=True), "not with measured"),
        (dict(resonance=(60.0, 0.05)), "needs t or rate"),
        (dict(t=np.where(tc > 1.0, tc + 0.002, tc), resonance=(60.0, 0.05)), "evenly spaced"),
    ]:
        with pytest.raises(ValueError, match=message):
            params.compensate(xc, **kwargs)
