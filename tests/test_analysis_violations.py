"""The matrix of violations (issue 31): for each assumption of the estimators (periodic
steady state, the same excitation in every block, one level, the layout claimed), a
synthetic record that breaks it by a known amount, and the expected answer (within 3 of
its own standard errors of the clean estimate, with a note naming what was handled) or
refusal (one line naming the real cause). One seed each here; tests/bench/bench_violations.py
runs every case over 10 seeds and prints the matrix and the LPM's cost.

The cases are built here (``CASES``, :func:`judge`) so that the bench uses the same ones."""
import warnings

import numpy as np
import pytest
from scipy import signal

from fftune.analysis import hosidf, robust_bla
from fftune.analysis.errors import InputError

FS = 1000.0
N = 500                      # samples per period
M, P = 4, 6                  # realizations, steady-state periods
LINES = np.arange(3, 120, 2)     # odd lines 3 .. 119 (6 .. 238 Hz)
NOISE = 0.02                 # output noise re the output rms
# a resonant band-pass plant: its transient from rest lasts about two periods
SOS = signal.cheby1(4, 1, [0.01, 0.3], btype="band", output="sos")


def multisine(seed, n=N):
    rng = np.random.default_rng(seed)
    X = np.zeros(n // 2 + 1, complex)
    X[LINES] = np.exp(2j * np.pi * rng.random(LINES.size))
    x = np.fft.irfft(X, n)
    return x / x.std()


def plant(u, seed, warm=20):
    """Output of the plant in steady state (``warm`` periods played first) plus noise."""
    rng = np.random.default_rng(1000 + seed)
    y = signal.sosfilt(SOS, np.concatenate((np.tile(u[:N], warm), u)))[warm * N:]
    return y + NOISE * np.std(y) * rng.standard_normal(y.size)


def plant_from_rest(u, seed):
    return plant(u, seed, warm=0)


def bla_data(seed, m=M, periods=P + 1, settle_state=True):
    """(M, T + P, N) input and output; every realization from steady state (or rest)."""
    us, ys = [], []
    for r in range(m):
        u = np.tile(multisine(seed * 100 + r), periods)
        y = plant(u, seed * 100 + r) if settle_state else plant_from_rest(u, seed * 100 + r)
        us.append(u.reshape(periods, N))
        ys.append(y.reshape(periods, N))
    return np.array(us), np.array(ys)


def clean(seed):
    u, y = bla_data(seed)
    return robust_bla(u, y, fs=FS, settle_periods=1)


def sigma(res):
    return np.sqrt(res.var_total if res.var_total is not None else res.var_noise)


def agrees(res, ref, share=0.9):
    """|G - G_clean| within 3 of its own standard errors at >= ``share`` of the lines."""
    if not np.array_equal(res.bins, ref.bins):
        return False, "other lines"
    z = np.abs(res.G - ref.G) / sigma(res)
    return bool(np.mean(z < 3) >= share), f"{100 * np.mean(z < 3):.0f} % within 3 sigma"


def run_bla(u, y, r=None, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return robust_bla(u, y, r, fs=FS, **kw)


# ---- the cases: each returns (ok, what happened) -------------------------------------

def case_burst(seed):
    """The excitation of realization 0 stops at 3.5 periods: its empty periods dropped."""
    u, y = bla_data(seed)
    u[0].reshape(-1)[int(3.5 * N):] = 0.0
    y[0] = plant(u[0].reshape(-1), seed).reshape(u.shape[1:])
    res = run_bla(u, y, settle_periods=1)
    ok, text = agrees(res, clean(seed))
    import re
    at = [int(m.group(1)) for n in res.notes for m in [re.search(r"stops at sample (\d+)", n)]
          if m]
    return ok and res.n_realizations == M - 1 and len(at) == 1 and 1740 <= at[0] <= 1750, text


def case_gap(seed):
    u, y = bla_data(seed)
    u[1, 3] = 0.0
    try:
        run_bla(u, y, settle_periods=1)
    except InputError as exc:
        return "gap in the excitation" in str(exc) and "realization 1, period 3" in str(exc), \
            str(exc)
    return False, "accepted"


def case_level_step(seed):
    u, y = bla_data(seed)
    u[2, 4:] *= 1.4
    try:
        run_bla(u, y, settle_periods=1)
    except InputError as exc:
        return "level changes at realization 2, period 4" in str(exc) and "+2.9 dB" in str(exc), \
            str(exc)
    return False, "accepted"


def case_mixed_levels(seed):
    """Realizations at two levels: the BLA says so (the HOSIDF refuses, below)."""
    u, y = bla_data(seed)
    u[2:] *= 2.0
    y[2:] *= 2.0
    res = run_bla(u, y, settle_periods=1)
    return any("2 different levels" in n for n in res.notes), res.notes[-1]


def case_wrong_m(seed):
    """M realizations given as one record: the realizations found from the phases."""
    u, y = bla_data(seed)
    res = run_bla(u.reshape(1, -1, N), y.reshape(1, -1, N), settle_periods=1)
    ok, text = agrees(res, clean(seed))
    return ok and res.n_realizations == M and \
        any("changes its phases every 7 periods" in n for n in res.notes), text


def case_shared_periods(seed):
    """Ten one-period records of one realization, the first from rest, given as ten
    realizations: taken as periods of one, the start from rest removed (LPM)."""
    u = np.tile(multisine(seed * 100), 10)
    y = plant_from_rest(u, seed * 100)
    res = run_bla(u.reshape(10, 1, N), y.reshape(10, 1, N))
    ref = run_bla(u.reshape(1, 10, N)[:, 3:], plant(u, seed * 100 + 7).reshape(1, 10, N)[:, 3:])
    z = np.abs(res.G - ref.G) / np.sqrt(res.var_noise + ref.var_noise)
    ok = np.mean(z < 3) >= 0.9 and res.n_periods == 10 and \
        any("share one excitation" in n for n in res.notes) and "lpm" in res.summary
    return bool(ok), f"{100 * np.mean(z < 3):.0f} % within 3 sigma"


def case_transient(seed):
    """Every realization starts from rest, no settle period given: the LPM."""
    u, y = bla_data(seed, periods=P + 1, settle_state=False)
    res = run_bla(u, y)
    ref = clean(seed)
    ok, text = agrees(res, ref)
    ratio = float(np.median(res.var_noise / ref.var_noise))
    return ok and "lpm" in res.summary and abs(ratio - 1) <= 0.3, f"{text}, noise x{ratio:.2f}"


def case_drift(seed):
    """A ramp of 10 % of the output rms over the record: the LPM."""
    u, y = bla_data(seed)
    y = y + 0.1 * y.std() * np.linspace(0, 1, y[0].size).reshape(y.shape[1:])
    res = run_bla(u, y, settle_periods=1)
    ref = clean(seed)
    ok, text = agrees(res, ref)
    ratio = float(np.median(res.var_noise / ref.var_noise))
    # removed by the LPM, or found under the noise at the excited lines (plain kept, said)
    said = res.summary.get("lpm", {}).get("removed") == "drift" or \
        any("drifts" in n and "plain averaging kept" in n for n in res.notes)
    return ok and said and abs(ratio - 1) <= 0.3, f"{text}, noise x{ratio:.2f}"


def case_wrong_n(seed):
    u, y = bla_data(seed)
    n = N - 7
    k = (u.size // n) // M
    try:
        run_bla(u.reshape(-1)[:M * k * n].reshape(M, k, n),
                y.reshape(-1)[:M * k * n].reshape(M, k, n))
    except InputError as exc:
        return f"does not repeat every N = {n}" in str(exc) and f"give N = {N}" in str(exc), \
            str(exc)
    return False, "accepted"


def sine(f0, n_blocks=10, n=1000, amp=1.0):
    t = np.arange(n_blocks * n) / FS
    u = amp * np.sin(2 * np.pi * f0 * t)
    return u, u + 0.2 * u ** 3


def case_sine_burst(seed):
    """A sine that stops at 7.43 s of 10 s, cut into 10 blocks: 3 blocks dropped, H_3/H_1
    as with the clean record; the same record as one block: refused naming the burst."""
    u, y = sine(20.0)
    u[7430:] = 0.0
    y[7430:] = 0.0
    ref = hosidf(*(x.reshape(1, 10, 1000) for x in sine(20.0)), fs=FS)
    res = hosidf(u.reshape(1, 10, 1000), y.reshape(1, 10, 1000), fs=FS)
    same = np.allclose(res.H, ref.H, rtol=1e-9) and np.isclose(np.ravel(res.amplitude)[0], 1.0)
    try:
        hosidf(u.reshape(1, 1, -1), y.reshape(1, 1, -1), fs=FS)
        one = False
    except InputError as exc:
        one = "stops at sample 7430" in str(exc)
    return bool(same and one and "dropped" in res.notes[0]), res.notes[0]


def case_sine_off_grid(seed):
    """9.75 and 2.5 periods per block: named off the grid before any averaging."""
    out = []
    for f0 in (9.75, 2.5):
        u, y = sine(f0)
        try:
            hosidf(u.reshape(1, 10, 1000), y.reshape(1, 10, 1000), fs=FS)
            out.append("accepted")
        except InputError as exc:
            out.append(str(exc))
    return all("off the DFT grid" in t for t in out), out[0]


def case_sine_levels(seed):
    """Ten amplitude levels given as repeats: refused, naming the levels."""
    parts = [sine(20.0, 2, amp=a) for a in np.linspace(0.1, 1.0, 10)]
    u = np.array([p[0].reshape(2, 1000) for p in parts])
    y = np.array([p[1].reshape(2, 1000) for p in parts])
    try:
        hosidf(u, y, fs=FS)
    except InputError as exc:
        return "10 different levels" in str(exc), str(exc)
    return False, "accepted"


def case_out_of_band(seed):
    """A full grid (every line 1 .. 60 excited), one realization, a cubic plant: no
    non-excited line in the band and no nonlinear variance; the lines up to 180, where
    the input is clean, show the distortion (and the linear plant's do not)."""
    from fftune.analysis import level_verdict
    rng = np.random.default_rng(seed)
    X = np.zeros(N // 2 + 1, complex)
    X[1:61] = np.exp(2j * np.pi * rng.random(60))
    x = np.fft.irfft(X, N)
    x = np.tile(x / x.std(), (1, P, 1))
    noise = 1e-3 * rng.standard_normal(x.shape)
    cubic = level_verdict(run_bla(x, x + 0.05 * x ** 3 + noise).summary)
    linear = level_verdict(run_bla(x, x + noise).summary)
    return (cubic["causes"] == ["nonlinear distortion (above the band)"]
            and linear["causes"] == ["cannot tell"]
            and "no distortion above the band either" in linear["text"]), cubic["text"]


def case_above_narrow_band(seed):
    """An odd grid whose band (lines 41 .. 59, every odd one excited) holds no line a
    square or a cube reaches (their products fall on excited lines, under 19 or over
    81): the band's detection lines see nothing, the lines above it (60 .. 177) do; a
    linear plant: 'linear', none above the band either."""
    from fftune.analysis import level_verdict
    rng = np.random.default_rng(seed)
    lines = np.arange(41, 60, 2)
    xs = []
    for _ in range(4):
        X = np.zeros(N // 2 + 1, complex)
        X[lines] = np.exp(2j * np.pi * rng.random(lines.size))
        x = np.fft.irfft(X, N)
        xs.append(np.tile(x / x.std(), (P, 1)))
    u = np.array(xs)
    out = []
    for f in (lambda v: v + 0.05 * v ** 2, lambda v: v - 0.03 * v ** 3, lambda v: 0.7 * v):
        res = run_bla(u, f(u) + 1e-3 * rng.standard_normal(u.shape))
        out.append((res.summary["nl_detected"], res.summary["above_band_detected"],
                    level_verdict(res.summary)["causes"]))
    nl = ["nonlinear distortion (above the band)"]
    return (out[0] == (False, True, nl) and out[1] == (False, True, nl)
            and out[2] == (False, False, ["linear"])), str(out)


def case_sine_gap_and_step(seed):
    out = []
    for make in (lambda u: u * ((np.arange(u.size) < 3000) | (np.arange(u.size) >= 5000)),
                 lambda u: u * np.where(np.arange(u.size) < 6000, 1.0, 1.5)):
        u, _ = sine(20.0)
        u = make(u)
        try:
            hosidf(u.reshape(1, 10, 1000), (u + 0.2 * u ** 3).reshape(1, 10, 1000), fs=FS)
            out.append("accepted")
        except InputError as exc:
            out.append(str(exc))
    return ("gap in the excitation" in out[0] and "block 3" in out[0]
            and "level changes at block 6 (sample 6000" in out[1]), out[0] + " | " + out[1]


def case_sine_drift(seed):
    """A sine test (3 Hz, 10 blocks, 5 repeats) whose output drifts by 10 % of its rms
    over the record: the plain block average is off by tens of standard errors at H_1;
    the LPM's H_k lie within 3 of them at every k."""
    rng = np.random.default_rng(seed)
    u, _ = sine(3.0)
    y = np.array([u + 0.1 * u ** 3 + 0.002 * rng.standard_normal(u.size) for _ in range(5)])
    us = np.tile(u, (5, 1)).reshape(5, 10, 1000)
    ref = hosidf(us, y.reshape(5, 10, 1000), fs=FS)
    yd = y + 0.1 * y.std() * np.linspace(0, 1, u.size)
    res = hosidf(us, yd.reshape(5, 10, 1000), fs=FS)
    se = ref.H_std / np.sqrt(5)
    k = 3 * np.arange(1, 8)
    Y = np.fft.rfft(yd.reshape(5, 10, 1000).sum(1), axis=-1)[:, k]
    U = np.fft.rfft(us.sum(1), axis=-1)[:, 3:4]
    plain = (Y * np.exp(-1j * np.arange(1, 8) * np.angle(U)) / np.abs(U)).mean(0)
    ok = np.all(np.abs(res.H - ref.H) < 3 * se) and np.abs(plain - ref.H)[0] > 10 * se[0] \
        and any("removed at the harmonics" in n for n in res.notes)
    return bool(ok), f"LPM {np.round(np.abs(res.H - ref.H) / se, 1)}"


def case_burst_middle(seed):
    """Realization 0 excited in periods 2 .. 5 only (a burst in the middle): its empty
    periods at both ends dropped (then the realization, shorter than the others)."""
    u, y = bla_data(seed)
    u[0, :2] = 0.0
    u[0, 6:] = 0.0
    y[0] = plant(u[0].reshape(-1), seed * 100).reshape(u.shape[1:])
    res = run_bla(u, y, settle_periods=1)
    ok, text = agrees(res, clean(seed))
    said = any("excitation starts at sample 1000" in n for n in res.notes) and \
        any("excitation stops at sample 3000" in n for n in res.notes)
    return ok and said and res.n_realizations == M - 1, text


def case_small_level_step(seed):
    """A step of 0.5 dB that stays (realization 2 from period 4): under the 1 dB re the
    median (each half of the periods is 0.25 dB off it), caught as a step between
    consecutive periods (0.2 dB and 10 times their scatter, here 0)."""
    u, y = bla_data(seed)
    u[2, 4:] *= 10 ** (0.5 / 20)
    y[2] = plant(u[2].reshape(-1), seed * 100 + 2).reshape(u.shape[1:])
    try:
        run_bla(u, y, settle_periods=1)
    except InputError as exc:
        return "level changes at realization 2, period 4" in str(exc) and "+0.5 dB" in str(exc), \
            str(exc)
    return False, "accepted"


def case_levels_one_record(seed):
    """Four realizations with the same phases at four levels, one record, no
    --realizations: refused as a level change (not averaged into one level)."""
    x = multisine(seed * 100)
    us = [np.tile(a * x, P + 1) for a in (1.0, 1.5, 2.0, 2.5)]
    ys = [plant(v, seed * 100 + i) for i, v in enumerate(us)]
    try:
        run_bla(np.concatenate(us).reshape(1, -1, N), np.concatenate(ys).reshape(1, -1, N),
                settle_periods=1)
    except InputError as exc:
        return "level changes at period" in str(exc) and "record each level" in str(exc), \
            str(exc)
    return False, "accepted"


def case_drift_in_u(seed):
    """A ramp of 10 % of its rms on the measured input (the plant sees it too): G as
    the clean one, and the input's drift named."""
    u, _ = bla_data(seed)
    u = u + 0.1 * u.std() * np.linspace(0, 1, u[0].size).reshape(u.shape[1:])
    y = np.array([plant(u[m].reshape(-1), seed * 100 + m).reshape(u.shape[1:])
                  for m in range(M)])
    res = run_bla(u, y, settle_periods=1)
    ok, text = agrees(res, clean(seed))
    return ok and any(n.startswith("input u drifts") for n in res.notes), text


def case_transient_in_u(seed):
    """A decaying oscillation on the input at the start (the plant from rest sees it),
    no settle period: the LPM, G as the clean one."""
    u, _ = bla_data(seed)
    t = np.arange(u[0].size)
    u = u + (0.5 * np.exp(-t / 300.0) * np.cos(0.2 * t)).reshape(u.shape[1:])
    y = np.array([plant_from_rest(u[m].reshape(-1), seed * 100 + m).reshape(u.shape[1:])
                  for m in range(M)])
    res = run_bla(u, y)
    ok, text = agrees(res, clean(seed))
    return ok and "lpm" in res.summary, text


def case_nan_in_a_period(seed):
    """A NaN in the input's period 3 of realization 1, an inf in the output's period 5
    of realization 2: refused naming the signal, realization, period and sample."""
    out = []
    for which, (m, b, k) in (("u", (1, 3, 17)), ("y", (2, 5, 100))):
        u, y = bla_data(seed)
        (u if which == "u" else y)[m, b, k] = np.nan if which == "u" else np.inf
        try:
            run_bla(u, y, settle_periods=1)
            out.append("accepted")
        except InputError as exc:
            out.append(str(exc))
    return ("input u: contains NaN" in out[0] and "realization 1, period 3" in out[0]
            and "sample 1517" in out[0] and "output y: contains NaN or inf" in out[1]
            and "realization 2, period 5" in out[1]), " | ".join(out)


def case_sample_slip(seed):
    """One period a sample short (realization 0, period 3): the later periods shift by
    one sample, in u and y alike; G as the clean one."""
    u, y = bla_data(seed)
    k = 3 * N + 250
    uf, yf = np.delete(u.reshape(-1), k), np.delete(y.reshape(-1), k)
    uf, yf = np.append(uf, uf[-1]), np.append(yf, yf[-1])
    res = run_bla(uf.reshape(u.shape), yf.reshape(y.shape), settle_periods=1)
    return agrees(res, clean(seed))


def case_clipped_u(seed):
    """The measured input clipped at 1.5 (1.5 times its rms) in two periods of
    realization 1, the plant driven by the clipped input: G as the clean one (u is
    what the plant received), or, where the clipping moves those periods' level by
    1 dB or more (the waveform's peaks differ by seed), refused naming the clipping."""
    u, _ = bla_data(seed)
    u[1, 3:5] = np.clip(u[1, 3:5], -1.5, 1.5)
    y = np.array([plant(u[m].reshape(-1), seed * 100 + m).reshape(u.shape[1:])
                  for m in range(M)])
    try:
        return agrees(run_bla(u, y, settle_periods=1), clean(seed))
    except InputError as exc:
        return "clipped at +-1.5 in realization 1, period 3" in str(exc), str(exc)


def case_sine_frequency_drift(seed):
    """A sine whose frequency drifts from 20 to 20.2 Hz over 10 s: refused naming the
    drift (the period moving from 999 to 991.05 samples)."""
    t = np.arange(10000) / FS
    u = np.sin(2 * np.pi * (20.0 * t + 0.01 * t ** 2))
    try:
        hosidf(u.reshape(1, 10, 1000), (u + 0.2 * u ** 3).reshape(1, 10, 1000), fs=FS)
    except InputError as exc:
        return "frequency drifts" in str(exc) and "to 991.052 samples" in str(exc), str(exc)
    return False, "accepted"


CASES = {
    "burst (periods dropped)": case_burst,
    "gap (refused)": case_gap,
    "level step (refused)": case_level_step,
    "mixed levels (note)": case_mixed_levels,
    "wrong M (inferred)": case_wrong_m,
    "shared realizations": case_shared_periods,
    "transient (LPM)": case_transient,
    "drift 10 % (LPM)": case_drift,
    "off-grid: wrong N": case_wrong_n,
    "sine burst": case_sine_burst,
    "sine off-grid": case_sine_off_grid,
    "sine levels as repeats": case_sine_levels,
    "sine gap / level step": case_sine_gap_and_step,
    "out-of-band distortion": case_out_of_band,
    "distortion above a narrow band": case_above_narrow_band,
    "sine drift 10 % (LPM)": case_sine_drift,
    "burst in the middle": case_burst_middle,
    "level step 0.5 dB (refused)": case_small_level_step,
    "levels in one record": case_levels_one_record,
    "drift in u (named)": case_drift_in_u,
    "transient in u (LPM)": case_transient_in_u,
    "NaN / inf in a period": case_nan_in_a_period,
    "one period 1 sample short": case_sample_slip,
    "u clipped in 2 periods": case_clipped_u,
    "sine frequency drift": case_sine_frequency_drift,
}


@pytest.mark.parametrize("name", list(CASES))
def test_violation_gets_the_right_answer_or_names_the_cause(name):
    ok, text = CASES[name](1)
    assert ok, text


def test_clean_data_get_no_check_note_and_the_same_numbers():
    u, y = bla_data(2)
    res = robust_bla(u, y, fs=FS, settle_periods=1)
    assert not any(("input u:" in n) or ("polynomial" in n) for n in res.notes)
    assert "lpm" not in res.summary
    # the estimate is the mean over realizations of the mean over periods of Y / U
    U = np.fft.rfft(u[:, 1:], axis=-1)[..., LINES]
    Y = np.fft.rfft(y[:, 1:], axis=-1)[..., LINES]
    np.testing.assert_allclose(res.G, (Y / U).mean(axis=1).mean(axis=0), rtol=1e-12)


def test_plain_averaging_is_biased_where_the_lpm_is_not():
    """The LPM matters: the plain average of records from rest is off by many sigma at
    the low lines (checked against the estimate of the same record with the transient
    periods dropped)."""
    u, y = bla_data(3, settle_state=False)
    ref = clean(3)
    lpm = run_bla(u, y)
    assert "lpm" in lpm.summary and lpm.summary["lpm"]["removed"] == "transient"
    # the plain mean of the periods, computed here, is biased by the transient
    U = np.fft.rfft(u, axis=-1)[..., LINES].mean(axis=1)
    Y = np.fft.rfft(y, axis=-1)[..., LINES].mean(axis=1)
    G_plain = (Y / U).mean(axis=0)
    z_plain = np.abs(G_plain - ref.G) / sigma(ref)
    z_lpm = np.abs(lpm.G - ref.G) / sigma(lpm)
    assert np.mean(z_plain < 3) < 0.8 and np.mean(z_lpm < 3) >= 0.9


def test_lpm_removes_a_known_polynomial_transient_exactly():
    """Noise-free: a transient that is a quadratic in the bin offset around every line
    (the record's DFT of an exponential, locally) is removed; the moments equal those of
    the periodic part to the fit's accuracy, and the noise variance is ~0."""
    from fftune.analysis.lpm import lpm_moments
    n, p = 256, 6
    lines = np.arange(5, 60, 4)
    X = np.zeros(n // 2 + 1, complex)
    X[lines] = np.exp(1j * lines)
    x = np.fft.irfft(X, n)
    u = np.tile(x, (1, p, 1))
    t = np.arange(p * n)
    tr = 0.3 * np.exp(-t / 400.0) * np.cos(0.05 * t)          # smooth in frequency
    y = (np.tile(2.0 * np.roll(x, 3), p) + tr).reshape(1, p, n)
    band = np.arange(lines[0], lines[-1] + 1)
    mom, G_per, info = lpm_moments(u, y, band=band, excited=lines)
    G_true = 2.0 * np.exp(-2j * np.pi * lines * 3 / n)
    np.testing.assert_allclose(G_per[0][0], G_true, rtol=2e-3)
    assert info.significant and info.lines_significant == lines.size
    # without the transient removal the plain mean is off by far more
    Yp = np.fft.rfft(y[0], axis=-1)[:, lines].mean(axis=0)
    assert np.max(np.abs(Yp / np.fft.rfft(x)[lines] - G_true)) > 10 * np.max(
        np.abs(G_per[0][0] - G_true))


def test_one_argument_check_for_every_entry():
    from fftune.analysis import robust_bla_spectra
    from fftune.analysis.bla import robust_bla_mimo
    u, y = bla_data(4, m=2, periods=3)
    U = np.fft.rfft(u, axis=-1)[..., 3:120]
    bins = np.arange(3, 120)
    for fs in (-5.0, float("nan"), 0.0, float("inf")):
        for call in (lambda: robust_bla(u, y, fs=fs),
                     lambda: robust_bla_spectra(U, U, bins=bins, n_period=N, fs=fs,
                                                excited_bins=LINES),
                     lambda: robust_bla_mimo(u[..., None], y[..., None], fs=fs),
                     lambda: hosidf(u, y, fs=fs)):
            with pytest.raises(InputError, match="fs must be a positive sample rate"):
                call()


def test_npz_matrix_in_n_by_p_orientation_is_read_by_columns(tmp_path, capsys):
    from fftune.host.cli import main
    z = np.load("tests/data/kul_motorbench_twomass.npz")
    np.savez(tmp_path / "t.npz", u=z["B_iq"].T, y=z["B_theta_motor"].T, fs=2500.0)
    np.savez(tmp_path / "r.npz", u=z["B_iq"], y=z["B_theta_motor"], fs=2500.0)
    outs = []
    for name in ("t.npz", "r.npz"):
        code = main(["analyze", "bla", str(tmp_path / name), "--period", "2500",
                     "--settle-periods", "1", "--json", str(tmp_path / (name + ".json"))])
        outs.append(capsys.readouterr().out)
        assert code == 0
    import json
    a = json.loads((tmp_path / "t.npz.json").read_text())
    b = json.loads((tmp_path / "r.npz.json").read_text())
    assert a["G"] == b["G"]
    assert "read column after column" in outs[0] and "read column" not in outs[1]
    # a matrix that fits neither way is refused, naming it
    np.savez(tmp_path / "bad.npz", u=z["B_iq"][:, :2400], y=z["B_theta_motor"][:, :2400],
             fs=2500.0)
    code = main(["analyze", "bla", str(tmp_path / "bad.npz"), "--period", "2500"])
    assert code == 2


def test_hosidf_cli_splits_levels(tmp_path):
    import subprocess
    import sys
    parts = [sine(20.0, 2, amp=a) for a in (0.5, 0.5, 1.0, 1.0, 2.0)]
    np.savez(tmp_path / "lv.npz", u=np.concatenate([p[0] for p in parts]),
             y=np.concatenate([p[1] for p in parts]), fs=FS)
    cmd = [sys.executable, "-m", "fftune.host.cli", "analyze", "hosidf", str(tmp_path / "lv.npz"),
           "--period", "1000", "--realizations", "5", "--json", str(tmp_path / "h.json")]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    assert "3 amplitude levels among the 5 repeats" in out
    import json
    levels = json.loads((tmp_path / "h.json").read_text())["levels"]
    assert [lv["repeats"] for lv in levels] == [[0, 1], [2, 3], [4]]
    assert [round(lv["amplitude"], 9) for lv in levels] == [0.5, 1.0, 2.0]
    # H_3 / H_1 of u + 0.2 u^3 at amplitude a: (0.05 a^2) / (1 + 0.15 a^2)
    for lv in levels:
        a = lv["amplitude"]
        h1, h3 = complex(*lv["H"][0]), complex(*lv["H"][2])
        assert abs(h3 / h1) == pytest.approx(0.05 * a * a / (1 + 0.15 * a * a), rel=1e-6)


def test_a_broken_pipe_ends_the_output_quietly(tmp_path, monkeypatch):
    """`fftune analyze ... | head`: the reader has gone; exit 0, no traceback."""
    import io
    import sys
    from fftune.host.cli import main
    u, y = sine(20.0, 2)
    np.savez(tmp_path / "s.npz", u=u, y=y, fs=FS)
    sink = open(tmp_path / "sink", "w")

    class Gone(io.StringIO):
        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def fileno(self):
            return sink.fileno()

    monkeypatch.setattr(sys, "stdout", Gone())
    for kind in ("hosidf", "bla"):
        args = ["analyze", kind, str(tmp_path / "s.npz"), "--period", "1000"]
        if kind == "bla":
            args += ["--lines", str(_lines_file(tmp_path))]
        assert main(args) == 0
    sink.close()


def _lines_file(tmp_path):
    path = tmp_path / "lines.txt"
    path.write_text("20\n")
    return path


def test_cli_infers_the_realizations_and_says_how(tmp_path, capsys):
    """M realizations in one record without --realizations (a new user's first try): the
    CLI path runs the same check and prints its note."""
    from fftune.host.cli import main
    u, y = bla_data(5)
    np.savez(tmp_path / "m.npz", u=u.reshape(-1), y=y.reshape(-1), fs=FS)
    code = main(["analyze", "bla", str(tmp_path / "m.npz"), "--period", str(N),
                 "--settle-periods", "1"])
    out = capsys.readouterr().out
    assert code == 0
    assert f"the excitation changes its phases every {P + 1} periods" in out
    assert f"taken as M = {M} realizations" in out
    assert f"M = {M}, P = {P}, T = 1, N = {N}" in out.splitlines()[0]


def test_a_noisy_input_is_said_not_refused():
    """A measured input whose noise makes its periods differ (correlation between 0.5 and
    0.9 at the strongest lines): no layout claim, no refusal; a note names the noise."""
    u, y = bla_data(6, m=2, periods=4)
    rng = np.random.default_rng(6)
    noisy = u + 1.0 * rng.standard_normal(u.shape)
    res = run_bla(noisy, y, settle_periods=1, excited_bins=LINES)
    assert res.n_realizations == 2 and res.n_periods == 3
    assert sum("differ more than a clean periodic" in n for n in res.notes) == 1
    # a clean input: no such note
    assert not any("differ more" in n for n in run_bla(u, y, settle_periods=1).notes)


def test_the_motor_bench_record_broken_in_known_ways():
    """Real data (record B of tests/data): a burst (excitation and output stop after
    period 15), the periods given as 20 one-period realizations (the first from rest),
    a level step at period 10, a start from rest without a settle period: each the
    clean estimate within 3 sigma at every line, with the note, or the refusal naming
    the period."""
    z = np.load("tests/data/kul_motorbench_twomass.npz")
    u, y = z["B_iq"].astype(float), z["B_theta_motor"].astype(float)
    ref = robust_bla(u[None], y[None], fs=2500.0, settle_periods=1)

    def close(res):
        zz = np.abs(res.G - ref.G) / np.sqrt(res.var_noise + ref.var_noise)
        return np.all(zz < 3)
    ub, yb = u.copy(), y.copy()
    ub[15:], yb[15:] = 0.0, yb[14, -1]
    res = run_bla(ub[None], yb[None], settle_periods=1)
    assert close(res) and res.n_periods == 14
    assert any("stops at sample 37500" in n for n in res.notes)
    res = run_bla(u[:, None, :], y[:, None, :])
    assert close(res) and res.n_realizations == 1 and res.n_periods == 20
    assert res.summary["lpm"]["removed"] == "transient"
    res = run_bla(u[None], y[None])
    assert close(res) and "lpm" in res.summary
    us = u.copy()
    us[10:] *= 1.3
    with pytest.raises(InputError, match=r"level changes at period 10 \(sample 25000 .*\+2\.3 dB"):
        robust_bla(us[None], y[None], fs=2500.0, settle_periods=1)


def test_a_directory_of_mixed_runs_names_the_option(tmp_path, capsys):
    """`fftune analyze bla DIR` on captures of two experiments (or levels) says which
    option chooses one (issue 36)."""
    import json as _json
    from fftune.analysis import capture
    from fftune.host.cli import main
    n, t, p = 64, 1, 3

    def meta(**kw):
        m = {"fs_hz": 1000.0, "n_period": n, "settle_periods": t, "record_periods": p,
             "experiment": "detect", "level_index": 0, "realization": 0, "parameters": {},
             "firmware_version": "fw", "eds_identity": _json.dumps({"vendor_id": 1}),
             "started_at": "2026-01-01T00:00:00+00:00", "metadata": {}}
        m.update(kw)
        return m
    rng = np.random.default_rng(0)
    sig = {name: rng.standard_normal((t + p) * n) for name in capture.STANDARD_SIGNALS}
    capture.write_run(tmp_path / "a.h5", sig, meta())
    capture.write_run(tmp_path / "b.h5", sig, meta(experiment="tune"))
    assert main(["analyze", "bla", str(tmp_path)]) == 2
    assert "choose one with --experiment NAME" in capsys.readouterr().err
    capture.write_run(tmp_path / "c.h5", sig, meta(level_index=1))
    assert main(["analyze", "bla", str(tmp_path), "--experiment", "detect"]) == 2
    assert "choose one level with --level L" in capsys.readouterr().err


def test_lpm_with_a_known_reference_and_a_measured_input():
    """Closed-loop form (r given, u measured with noise), records from rest: the LPM's
    moments go through the known-reference estimator; G within 3 sigma of the clean
    estimate at >= 90 % of the lines."""
    u, y = bla_data(7, settle_state=False)
    um = u + 0.01 * np.random.default_rng(7).standard_normal(u.shape)
    res = run_bla(um, y, r=u)
    ref = clean(7)
    assert res.known_reference and res.summary["lpm"]["removed"] == "transient"
    z = np.abs(res.G - ref.G) / np.sqrt(res.var_total)
    assert np.mean(z < 3) >= 0.9


def test_hosidf_cli_drops_a_burst_and_says_so_in_the_json(tmp_path, capsys):
    import json
    from fftune.host.cli import main
    u, y = sine(20.0)
    u[7430:] = 0.0
    y[7430:] = 0.0
    np.savez(tmp_path / "b.npz", u=u, y=y, fs=FS)
    code = main(["analyze", "hosidf", str(tmp_path / "b.npz"), "--period", "1000",
                 "--json", str(tmp_path / "b.json")])
    out = capsys.readouterr().out
    doc = json.loads((tmp_path / "b.json").read_text())
    assert code == 0 and doc["amplitude"] == pytest.approx(1.0, rel=1e-9)
    assert "stops at sample 7430" in doc["notes"][0] and "stops at sample 7430" in out


def test_above_the_band_with_a_reference_leaves_out_the_measured_inputs_content():
    """Closed-loop form: r clean above the band, the measured u carrying content there
    (a loop's feedback, here a known periodic signal at lines 125 .. 160) that the plant
    passes on linearly: those lines are left out (counted), not read as distortion
    (without the accounting 30 % or more of them stand 6 dB over the output's noise);
    an output distortion at lines where u is clean (215 .. 245) is seen."""
    rng = np.random.default_rng(11)
    u, y = bla_data(11)
    r = u.copy()
    X = np.zeros(N // 2 + 1, complex)
    X[125:161] = 0.05 * N * np.exp(2j * np.pi * rng.random(36))
    _, h = signal.sosfreqz(SOS, worN=np.arange(N // 2 + 1) * 2 * np.pi / N)
    um, ylin = u + np.fft.irfft(X, N), y + np.fft.irfft(X * h, N)
    res = run_bla(um, ylin, r=r, settle_periods=1)
    s = res.summary
    assert s["above_band_lines_input_content"] == 36
    assert s["above_band_lines"] + s["above_band_lines_input_content"] + \
        s["above_band_lines_excitation_not_clean"] == 249 - 119
    assert s["above_band_detected"] is False
    # the same lines without the accounting: many 6 dB over the output's noise
    Y = np.fft.rfft(ylin[:, 1:], axis=-1)[..., 125:161]
    dev = Y - Y.mean(axis=1, keepdims=True)
    noise = (np.abs(dev) ** 2).sum(1).mean(0) / (P * (P - 1))
    assert np.mean((np.abs(Y.mean(1)) ** 2).mean(0) > 4 * noise) >= 0.3
    Z = np.zeros(N // 2 + 1, complex)
    Z[215:246] = 0.01 * N * np.exp(2j * np.pi * rng.random(31))
    res = run_bla(um, ylin + np.fft.irfft(Z, N), r=r, settle_periods=1)
    assert res.summary["above_band_detected"] is True
