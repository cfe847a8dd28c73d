"""The matrix of violations (issue 31; `make bench`): every case of
tests/test_analysis_violations.py over 10 seeds (the share with the expected answer or
refusal), the LPM's acceptance figures over seeds (records from rest and with a drift of
10 % of the output rms, against the clean steady-state estimate), and the costs: the
checks before averaging on clean data, and the robust BLA through the local polynomial
method against the plain robust BLA."""
import os
import sys
import time
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, os.path.join(REPO, "tests"))

import test_analysis_violations as tv  # noqa: E402

from fftune.analysis import robust_bla  # noqa: E402
from fftune.analysis.checks import check_blocks  # noqa: E402


def matrix(seeds=10):
    print(f"violations (M = {tv.M}, P = {tv.P}, N = {tv.N}, {tv.LINES.size} odd lines, noise "
          f"{100 * tv.NOISE:g} % of the output rms), {seeds} seeds:")
    for name, case in tv.CASES.items():
        good, last = 0, ""
        t0 = time.perf_counter()
        for seed in range(seeds):
            ok, text = case(seed)
            good += bool(ok)
            last = text if not ok else last
        ms = 1e3 * (time.perf_counter() - t0) / seeds
        print(f"  {name:28s} {good:2d}/{seeds} right ({ms:6.1f} ms)"
              + (f"  last miss: {str(last)[:120]}" if good < seeds else ""))


def lpm_acceptance(seeds=10):
    print("LPM acceptance (share of lines within 3 sigma of the clean estimate; median "
          "var_noise re the clean one):")
    for label, make in (("start from rest, T = 0", _from_rest), ("drift 10 % of output rms", _drift)):
        shares, ratios, plain = [], [], []
        for seed in range(seeds):
            u, y, settle = make(seed)
            ref = tv.clean(seed)
            res = tv.run_bla(u, y, settle_periods=settle)
            z = np.abs(res.G - ref.G) / tv.sigma(res)
            shares.append(np.mean(z < 3))
            ratios.append(np.median(res.var_noise / ref.var_noise))
            U = np.fft.rfft(u[:, settle:], axis=-1)[..., tv.LINES]
            Y = np.fft.rfft(y[:, settle:], axis=-1)[..., tv.LINES]
            zp = np.abs((Y / U).mean(axis=1).mean(axis=0) - ref.G) / tv.sigma(ref)
            plain.append(np.mean(zp < 3))
        print(f"  {label:26s} within 3 sigma: min {100 * min(shares):.0f} %, median "
              f"{100 * np.median(shares):.0f} %; noise variance x{min(ratios):.2f} .. "
              f"x{max(ratios):.2f}; plain average within 3 sigma: median "
              f"{100 * np.median(plain):.0f} %")


def _from_rest(seed):
    u, y = tv.bla_data(seed, settle_state=False)
    return u, y, 0


def _drift(seed):
    u, y = tv.bla_data(seed)
    y = y + 0.1 * y.std() * np.linspace(0, 1, y[0].size).reshape(y.shape[1:])
    return u, y, 1


def _timed(fn, rounds):
    out = []
    for _ in range(rounds):
        t0 = time.process_time()
        fn()
        out.append(time.process_time() - t0)
    return float(np.median(out))


def costs(m=10, p=10, n=8192, rounds=15):
    """CPU time medians: the plain robust BLA on steady-state records, the same call on
    records from rest (the checks find the transient: plain estimate + LPM + estimate
    from the LPM's moments), the checks alone on the input."""
    from scipy import signal
    rng = np.random.default_rng(5)
    lines = np.arange(1, 1000, 2) * (n // 1000) + 1                 # odd lines up to ~fs/2/4
    lines = lines[(lines % 2 == 1) & (lines < n // 2)]
    sos = signal.cheby1(4, 1, [0.002, 0.3], btype="band", output="sos")
    us, ys, ys_rest = [], [], []
    for r in range(m):
        X = np.zeros(n // 2 + 1, complex)
        X[lines] = np.exp(2j * np.pi * rng.random(lines.size))
        x = np.fft.irfft(X, n)
        x /= x.std()
        u = np.tile(x, p)
        warm = signal.sosfilt(sos, np.tile(x, p + 5))[5 * n:]
        rest = signal.sosfilt(sos, u)
        noise = 0.02 * warm.std() * rng.standard_normal(u.size)
        us.append(u.reshape(p, n))
        ys.append((warm + noise).reshape(p, n))
        ys_rest.append((rest + noise).reshape(p, n))
    u, y, y_rest = np.array(us), np.array(ys), np.array(ys_rest)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = robust_bla(u, y_rest, fs=1000.0)
        assert "lpm" in res.summary, "the record from rest must take the LPM path"
        assert "lpm" not in robust_bla(u, y, fs=1000.0).summary
        # alternating in every round (the load moves); medians and the per-round ratio
        u_meas = u + 1e-3 * rng.standard_normal(u.shape)     # a measured input: its own
        times = {k: [] for k in ("plain", "lpm", "plain_m", "lpm_m", "check", "fft")}
        calls = {"plain": lambda: robust_bla(u, y, fs=1000.0),
                 "lpm": lambda: robust_bla(u, y_rest, fs=1000.0),
                 "plain_m": lambda: robust_bla(u_meas, y, fs=1000.0),
                 "lpm_m": lambda: robust_bla(u_meas, y_rest, fs=1000.0),
                 "check": lambda: check_blocks(u, fs=1000.0),
                 "fft": lambda: (np.fft.rfft(u, axis=-1), np.fft.rfft(y, axis=-1))}
        for _ in range(rounds):
            for key, call in calls.items():
                times[key].append(_timed(call, 1))
        t_plain, t_lpm, t_check, t_fft = (float(np.median(times[k]))
                                          for k in ("plain", "lpm", "check", "fft"))
        per_round = float(np.median(np.array(times["lpm"]) / np.array(times["plain"])))
        t_plain_m, t_lpm_m = float(np.median(times["plain_m"])), float(np.median(times["lpm_m"]))
        per_round_m = float(np.median(np.array(times["lpm_m"]) / np.array(times["plain_m"])))
    print(f"costs (CPU time, median of {rounds} alternating rounds; M = {m}, P = {p}, N = {n}, {lines.size} "
          f"excited lines; load average {os.getloadavg()[0]:.1f}):")
    print(f"  plain robust BLA (steady state)      {1e3 * t_plain:7.1f} ms  "
          f"({t_plain / t_fft:.2f}x the rffts of u and y)")
    print(f"  robust BLA with the LPM (from rest, u exactly periodic) {1e3 * t_lpm:7.1f} ms  "
          f"({t_lpm / t_plain:.2f}x the plain robust BLA, per round {per_round:.2f}x; "
          f"goal <= 3x)")
    print(f"  the same with a measured input (u noisy: its transient fitted too): plain "
          f"{1e3 * t_plain_m:.1f} ms, LPM {1e3 * t_lpm_m:.1f} ms ({t_lpm_m / t_plain_m:.2f}x, "
          f"per round {per_round_m:.2f}x)")
    print(f"  checks before averaging (input only) {1e3 * t_check:7.1f} ms  "
          f"({100 * t_check / t_plain:.0f} % of the plain robust BLA)")


if __name__ == "__main__":
    matrix()
    lpm_acceptance()
    costs()
