"""numpy in and out: dtypes and shapes accepted, the wrong ones refused with TypeError or
ValueError naming the argument (never a Rust panic)."""

import numpy as np
import pytest

import twinstack
from conftest import REPO


@pytest.fixture(scope="module")
def params():
    # A P-I model without creep or lag, 0...140 V onto ±45 µm (the simulated board's).
    with twinstack.Board("sim") as b:
        settings = b.params()
    from conftest import param_json

    return twinstack.Params.from_json(param_json(settings))


def record(n=400):
    t = np.arange(n) * 1e-3
    u = 70.0 + 60.0 * np.sin(2 * np.pi * t * 5.0)
    return t, u


def test_integer_float32_and_list_inputs_give_float64_arrays(params):
    _, u = record()
    x = params.predict(u)
    assert x.dtype == np.float64 and x.shape == u.shape
    single = u.astype(np.float32)
    assert np.array_equal(params.predict(single), params.predict(single.astype(np.float64)))
    ints = np.round(u).astype(np.int32)
    assert np.array_equal(params.predict(ints), params.predict(ints.astype(np.float64)))
    assert np.array_equal(params.predict(list(u)), x)
    # Strided views are read as they look.
    assert np.array_equal(params.predict(np.repeat(u, 2)[::2]), x)
    drive = params.compensate(x)
    assert drive.dtype == np.float64 and drive.shape == x.shape


@pytest.mark.parametrize(
    "bad, error, words",
    [
        (np.zeros(10, dtype=complex), TypeError, "u: dtype complex128 is not a real number type"),
        (np.array(["1", "2"]), TypeError, "u: dtype <U1 is not a real number type"),
        (np.zeros(10, dtype=bool), TypeError, "dtype bool"),
        (np.array([object(), object()]), TypeError, "dtype object"),
        (np.zeros((3, 4)), ValueError, "u must be one-dimensional, got shape (3, 4)"),
        (np.float64(3.0), ValueError, "u must be one-dimensional, got shape ()"),
        (np.array([]), ValueError, "u is empty"),
        ([[1.0, 2.0], [3.0]], TypeError, "u: cannot be read as an array of numbers"),
        ("not an array", TypeError, "u: dtype <U12"),
    ],
)
def test_wrong_dtypes_and_shapes_are_refused_by_name(params, bad, error, words):
    with pytest.raises(error) as e:
        params.predict(bad)
    assert words in str(e.value)


def test_time_arguments_are_checked(params):
    t, u = record(50)
    assert np.array_equal(params.predict(u, t=t), params.predict(u))
    assert np.array_equal(params.predict(u, rate=1000.0), params.predict(u))
    with pytest.raises(ValueError, match="t has 49 samples, the signal 50"):
        params.predict(u, t=t[:-1])
    bad = t.copy()
    bad[10] = bad[9]
    with pytest.raises(ValueError, match=r"t\[10\] = 0.009\d* s does not increase"):
        params.predict(u, t=bad)
    with pytest.raises(ValueError, match="not both"):
        params.predict(u, t=t, rate=1000.0)
    with pytest.raises(ValueError, match="rate"):
        params.predict(u, rate=-1.0)


def test_a_sample_that_is_not_a_number_is_refused_naming_it(params):
    # It would run through the model's memory into every later sample (and through the
    # sensor lag's alignment into earlier ones): refused, naming the array and the index.
    t, u = record(50)
    x = params.predict(u, t=t)
    for bad in (np.nan, np.inf):
        u2 = u.copy()
        u2[5] = bad
        with pytest.raises(ValueError, match=r"`u`\[5\] is not finite"):
            params.predict(u2, t=t)
        x2 = x.copy()
        x2[7] = bad
        with pytest.raises(ValueError, match=r"`x`\[7\] is not finite"):
            params.compensate(x2, t=t)
        with pytest.raises(ValueError, match=r"`x`\[7\] is not finite"):
            params.compensate(x2, t=t, measured=True)


def test_identify_checks_its_arrays(params):
    t, u = record()
    x = params.predict(u)
    with pytest.raises(ValueError, match="`x` has 399 samples, `t` has 400"):
        twinstack.identify(t, u, x[:-1])
    nan = x.copy()
    nan[7] = np.nan
    with pytest.raises(ValueError, match=r"`x`\[7\] is not finite"):
        twinstack.identify(t, u, nan)
    with pytest.raises(ValueError, match="only 5 samples"):
        twinstack.identify(t[:5], u[:5], x[:5])
    with pytest.raises(TypeError, match="t: dtype complex128"):
        twinstack.identify(t.astype(complex), u, x)
    with pytest.raises(ValueError, match="unknown model 'spline': expected auto, pi"):
        twinstack.identify(t, u, x, model="spline")
    with pytest.raises(ValueError, match="thresholds"):
        twinstack.identify(t, u, x, thresholds="log")
    with pytest.raises(ValueError, match="operators 0"):
        twinstack.identify(t, u, x, model="pi", operators=0)


def test_a_model_with_creep_needs_the_sample_period():
    text = (REPO / "python" / "tests" / "creep-params.json").read_text()
    p = twinstack.Params.from_json(text)
    assert p.creep
    u = np.linspace(0.0, 100.0, 100)
    with pytest.raises(ValueError, match="give t"):
        p.predict(u)
    fast = p.predict(u, rate=1000.0)
    slow = p.predict(u, rate=500.0)
    assert fast.shape == (100,) and not np.array_equal(fast, slow)
    # A creep mode shorter than two samples is refused, not run.
    with pytest.raises(ValueError, match="shorter than 2 ticks"):
        p.predict(u, rate=10.0)
