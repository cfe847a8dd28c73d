"""Synthetic systems whose nonlinear-detection answer is known (issue 23's ground-truth
matrix): open-loop periodic experiments built in the frequency domain (no transient, exact
periodicity), analysed with :func:`fftune.analysis.bla.robust_bla` and judged by
:func:`fftune.analysis.bla.level_verdict`.

Used by tests/test_analysis_groundtruth.py (a fast subset, a few seconds) and
tests/bench/bench_detect_matrix.py (the whole matrix over seeds, `make bench`).
"""
import numpy as np

from fftune.analysis.bla import bla_levels, level_verdict, robust_bla
from fftune.analysis.multisine import multisine_realizations

N, M, P, FS = 2048, 6, 4, 1000.0
K_MAX = 300


def periodic_filter(x, b=(0.05, 0.1), a=(1.0, -1.2, 0.45)):
    """Steady-state response of the IIR filter b/a to the periodic signal x (last axis one
    period): exact, no transient."""
    n = x.shape[-1]
    w = np.exp(-2j * np.pi * np.arange(n // 2 + 1) / n)
    h = np.polyval(np.asarray(b)[::-1], w) / np.polyval(np.asarray(a)[::-1], w)
    return np.fft.irfft(np.fft.rfft(x, axis=-1) * h, n=n, axis=-1)


def excitation(seed, rms=0.5, kind="random_odd", m=M, n=N, k_max=K_MAX):
    """(M, N) periods of a multisine and its excited bins."""
    d = multisine_realizations(m, FS, n, k_min=1, k_max=k_max, kind=kind, seed=seed, rms=rms)
    return np.stack([x.period for x in d]), d[0].excited


def _repeat(x, p=P):
    return np.repeat(x[:, None, :], p, axis=1)


def _noise(rng, shape, std):
    return std * rng.standard_normal(shape)


def system(name, seed=0, rms=0.5, noise=1e-4):
    """One experiment of a named system: (u, y, kwargs for robust_bla, the expectation).

    The expectation is a dict: ``causes_any`` (at least one of these causes),
    ``causes_none`` (none of these), and optional ``summary`` checks {key: value}.
    """
    rng = np.random.default_rng(1000 + seed)
    kw = {"fs": FS}
    if name == "full grid cubic":
        u, _ = excitation(seed, rms, kind="full")
    elif name == "full grid linear":
        u, _ = excitation(seed, rms, kind="full")
    else:
        u, _ = excitation(seed, rms)
    x = periodic_filter(u)
    plant_claims = ("plant odd nonlinearity", "plant even nonlinearity",
                    "plant nonlinearity (parity not classifiable with this grid)")
    if name == "linear":
        y, expect = x, {"causes_any": ["linear"], "causes_none": plant_claims}
    elif name == "odd only":
        y = x + 4.0 * x ** 3
        expect = {"causes_any": ["plant odd nonlinearity"],
                  "causes_none": ["plant even nonlinearity"]}
    elif name == "even only":
        y = x + 2.0 * x ** 2
        expect = {"causes_any": ["plant even nonlinearity"],
                  "causes_none": ["plant odd nonlinearity"]}
    elif name == "odd and even":
        y = x + 4.0 * x ** 3 + 2.0 * x ** 2
        expect = {"causes_any": ["plant odd nonlinearity"],
                  "summary": {"plant_even_detected": True}}
    elif name == "saturation":
        lim = 0.6 * np.max(np.abs(x))
        y = np.clip(x, -lim, lim)
        expect = {"causes_any": ["plant odd nonlinearity"],
                  "causes_none": ["plant even nonlinearity"]}
    elif name == "quantisation":
        q = 0.08 * np.std(x)                 # a coarse encoder: ~50 counts over +-2 sigma
        y = q * np.round(x / q)
        kw["y_quantisation_step"] = q
        expect = {"causes_any": ["linear", "quantisation floor", "input distortion "
                                 "(before the measured input)"],
                  "causes_none": plant_claims}
        noise = 0.0
    elif name == "cross-coupling":
        # a second input on the same grid with its own phases, not measured
        d = multisine_realizations(2 * M, FS, N, k_min=1, k_max=K_MAX, seed=seed, rms=rms)
        u2 = np.stack([x.period for x in d[M:]])
        y = x + 0.8 * periodic_filter(u2, b=(0.2,), a=(1.0, -0.6))
        expect = {"causes_any": ["unmeasured inputs"], "causes_none": plant_claims}
    elif name == "input distortion":
        # the measured input is a distorted force (the actuator): the plant is linear
        u = u + 0.03 * u ** 3 / np.std(u) ** 2
        x = periodic_filter(u)
        y = x
        expect = {"causes_any": ["linear", "input distortion (before the measured input)"],
                  "causes_none": plant_claims,
                  "summary": {"excitation_distorted": True}}
    elif name == "band-limited input":
        u, exc = _band_limited(rng, seed, rms)
        x = periodic_filter(u)
        y = x
        expect = {"causes_any": ["linear", "input distortion (before the measured input)"],
                  "causes_none": plant_claims, "excited": exc}
    elif name == "full grid cubic":
        y = x + 4.0 * x ** 3
        expect = {"causes_any": ["nonlinear distortion (excited lines)"]}
    elif name == "full grid linear":
        y = x
        expect = {"causes_any": ["linear"]}
    else:
        raise ValueError(name)
    u_rec = _repeat(u)
    y_rec = _repeat(y) + _noise(rng, (u.shape[0], P, N), noise)
    return u_rec, y_rec, kw, expect


def _band_limited(rng, seed, rms):
    """A random odd multisine up to bin 200 whose force carries distortion 50 dB under the
    excited lines on every line up to N/4, and a stop band 160 dB under them above."""
    u, exc = excitation(seed, rms, k_max=200)
    spec = np.fft.rfft(u, axis=-1)
    k = np.arange(spec.shape[-1])
    ref = np.median(np.abs(spec[:, exc]))
    dist = ref * 10 ** (-50 / 20) * (rng.standard_normal(spec.shape)
                                     + 1j * rng.standard_normal(spec.shape)) / np.sqrt(2)
    dist[:, k > N // 4] *= 10 ** (-110 / 20)
    dist[:, 0] = 0
    dist[:, -1] = 0
    keep = np.zeros(spec.shape[-1], bool)
    keep[exc] = True
    spec = np.where(keep, spec, dist)
    return np.fft.irfft(spec, n=N, axis=-1), exc


SYSTEMS = ("linear", "odd only", "even only", "odd and even", "saturation", "quantisation",
           "cross-coupling", "input distortion", "band-limited input", "full grid cubic",
           "full grid linear")


def judge(name, seed=0):
    """Run one system; returns (ok, causes, text, result)."""
    u, y, kw, expect = system(name, seed)
    res = robust_bla(u, y, warn_transient=False, **kw)
    v = level_verdict(res.summary)
    ok = any(c in v["causes"] for c in expect["causes_any"])
    ok &= not any(c in v["causes"] for c in expect.get("causes_none", ()))
    for key, value in expect.get("summary", {}).items():
        ok &= res.summary.get(key) == value
    if "excited" in expect:
        ok &= np.array_equal(res.bins, expect["excited"])
    return bool(ok), v["causes"], v["text"], res


def cross_coupling_levels(seed=0, levels=(0.1, 0.3, 1.0)):
    """The cross-coupled system at several levels with the second input on ANOTHER grid
    (its lines fall on the measured input's detection lines): only the level dependence
    tells it from a nonlinearity."""
    rng = np.random.default_rng(seed)
    u_lv, y_lv = [], []
    for lvl in levels:
        u1, _ = excitation(seed, lvl)
        u2, _ = excitation(seed + 77, lvl)         # other seed: other removed lines
        y = periodic_filter(u1) + 0.7 * periodic_filter(u2, b=(0.1, 0.1), a=(1.0, -0.8))
        u_lv.append(_repeat(u1))
        y_lv.append(_repeat(y) + _noise(rng, (u1.shape[0], P, N), 1e-4))
    return bla_levels(u_lv, y_lv, fs=FS, warn_transient=False)
