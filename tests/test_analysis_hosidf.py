"""HOSIDF against analytic describing functions (docs/method.md section 3)."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fftune.analysis.errors import InputError
from fftune.analysis.hosidf import hosidf

N_FINE = 2 ** 17      # samples per sine period: keeps aliasing of slow 1/k harmonics < 1e-8


def sine_record(amplitude, n=N_FINE, periods=1):
    # half-sample offset: no sample on a zero crossing (sign(0) = 0) or symmetric kink
    theta = 2 * np.pi * (np.arange(n * periods) + 0.5) / n
    return theta, amplitude * np.sin(theta)


def run(f, amplitude, k=7, n=N_FINE):
    _, u = sine_record(amplitude, n)
    return hosidf(u.reshape(1, 1, -1), f(u).reshape(1, 1, -1), fs=float(n), n_harmonics=k)


def odd_expected(b_k, amplitude, k_max=7):
    """H_k = (-1)^((k-1)/2) b_k / A for odd k, 0 for even k."""
    h = np.zeros(k_max)
    for k in range(1, k_max + 1, 2):
        h[k - 1] = (-1) ** ((k - 1) // 2) * b_k(k) / amplitude
    return h


def sat_s(k, beta):
    return 2 / np.pi * (np.sin((k - 1) * beta) / (k * (k - 1)) + np.sin((k + 1) * beta) / (k * (k + 1)))


def sat_expected(a, amplitude, k_max=7):
    beta = np.arcsin(a / amplitude)
    h = np.zeros(k_max)
    h[0] = 2 / np.pi * (beta + np.sin(beta) * np.cos(beta))
    for k in range(3, k_max + 1, 2):
        h[k - 1] = (-1) ** ((k - 1) // 2) * sat_s(k, beta)
    return h


def assert_hosidf(res, expected, rtol):
    h = res.H
    scale = np.abs(expected[0])
    np.testing.assert_allclose(h.real, expected, rtol=rtol, atol=rtol * 1e-3 * scale)
    np.testing.assert_allclose(h.imag, 0.0, atol=rtol * 1e-3 * scale)
    odd = np.abs(expected) > 0
    np.testing.assert_allclose(np.abs(h[odd]), np.abs(expected[odd]), rtol=rtol)


@pytest.mark.parametrize("amplitude", [0.5, 2.0])
def test_relay_coulomb(amplitude):
    F = 1.3
    res = run(lambda x: F * np.sign(x), amplitude)
    expected = odd_expected(lambda k: 4 * F / (k * np.pi), amplitude)
    assert_hosidf(res, expected, 1e-6)
    phases = np.degrees(np.angle(res.H[[0, 2, 4, 6]]))
    np.testing.assert_allclose(np.abs(phases), [0, 180, 0, 180], atol=1e-4)
    assert float(res.amplitude) == pytest.approx(amplitude, rel=1e-12)


def test_cubic():
    c, A = 0.7, 1.9
    res = run(lambda x: c * x ** 3, A, n=1024)
    expected = np.zeros(7)
    expected[0], expected[2] = 3 * c * A ** 2 / 4, c * A ** 2 / 4
    np.testing.assert_allclose(res.H.real, expected, atol=1e-12)
    np.testing.assert_allclose(res.H.imag, 0, atol=1e-12)


@pytest.mark.parametrize("amplitude", [1.5, 4.0])
def test_saturation(amplitude):
    a = 1.0
    res = run(lambda x: np.clip(x, -a, a), amplitude)
    assert_hosidf(res, sat_expected(a, amplitude), 1e-6)


@pytest.mark.parametrize("amplitude", [1.5, 4.0])
def test_dead_zone(amplitude):
    d = 1.0
    res = run(lambda x: np.sign(x) * np.maximum(np.abs(x) - d, 0.0), amplitude)
    expected = -sat_expected(d, amplitude)
    expected[0] += 1.0
    assert_hosidf(res, expected, 1e-6)


def coulomb_mass_position(theta, force, fc, mass, omega):
    """Exact steady-state position of m x'' = U sin(w t) - Fc sign(x'), no sticking."""
    theta0 = np.arccos(np.pi * fc / (2 * force))

    def rising(th):          # velocity >= 0 on [theta0, theta0 + pi]
        s = th - theta0
        return (force * (np.cos(theta0) * s - np.sin(th) + np.sin(theta0)) - fc * s ** 2 / 2) / (
            mass * omega ** 2)

    phase = np.mod(theta - theta0, 2 * np.pi)
    x = np.where(phase <= np.pi, rising(theta0 + phase),
                 -rising(theta0 + phase - np.pi) + rising(theta0 + np.pi))
    return x, theta0


@pytest.mark.parametrize("ratio", [2.0, 5.0])
def test_free_mass_with_coulomb_friction(ratio):
    fc, mass, omega = 1.0, 0.8, 2 * np.pi * 3.0
    force = ratio * fc
    n = 4096
    theta, u = sine_record(force, n)
    x, theta0 = coulomb_mass_position(theta, force, fc, mass, omega)
    res = hosidf(u.reshape(1, 1, -1), x.reshape(1, 1, -1), fs=3.0 * n, n_harmonics=7)
    h1 = -(1 - 4 * fc / (np.pi * force) * np.exp(-1j * theta0)) / (mass * omega ** 2)
    assert abs(res.H[0] - h1) <= 1e-3 * abs(h1)
    for k in (3, 5, 7):
        mag = 4 * fc / (np.pi * mass * omega ** 2 * k ** 3 * force)
        assert abs(res.H[k - 1]) == pytest.approx(mag, rel=1e-3)
        assert abs(res.H[k - 2]) < 1e-9 * abs(h1)            # even harmonics vanish


def simulate_coulomb_mass_from_rest(force, fc, mass, f, periods):
    """m x'' = U sin(w t) - Fc sign(x') from rest, with scipy solve_ivp.

    Piecewise smooth: one solve_ivp per direction of motion, ended by the event v = 0;
    at rest the mass sticks until |U sin(w t)| exceeds Fc. Returns the dense solutions.
    """
    omega = 2 * np.pi * f
    release = np.arcsin(fc / force)
    t, x, segments = release / omega, 0.0, []
    while t < periods / f:
        s = np.sign(force * np.sin(omega * t))

        def rhs(tt, z, s=s):
            return [z[1], (force * np.sin(omega * tt) - fc * s) / mass]

        def stop(tt, z):
            return z[1]
        stop.terminal, stop.direction = True, -s
        sol = solve_ivp(rhs, (t, periods / f), [x, 0.0], events=stop, dense_output=True,
                        rtol=1e-10, atol=1e-12, first_step=1e-9)
        segments.append((t, sol.t[-1], sol.sol))
        t, x = sol.t[-1], sol.y[0, -1]
        if abs(force * np.sin(omega * t)) <= fc:       # sticks until the force exceeds Fc
            phase = (omega * t) % (2 * np.pi)
            t += (min(p for p in (release, np.pi + release, 2 * np.pi + release)
                      if p > phase) - phase) / omega
    return segments


def test_free_mass_simulated_with_solve_ivp_from_rest_matches_formula():
    """The same oracle from the ODE itself, started at rest, last of 20 periods."""
    fc, mass, force, f, n, periods = 1.0, 1.0, 3.0, 1.0, 2048, 20
    segments = simulate_coulomb_mass_from_rest(force, fc, mass, f, periods)
    t = (periods - 1) / f + (np.arange(n) + 0.5) / (n * f)
    x = np.full(n, np.nan)
    for start, end, dense in segments:
        inside = (t >= start) & (t <= end)
        if inside.any():
            x[inside] = dense(t[inside])[0]
    assert np.isfinite(x).all()                           # moving all the last period
    omega = 2 * np.pi * f
    u = force * np.sin(omega * t)
    res = hosidf(u.reshape(1, 1, -1), x.reshape(1, 1, -1), fs=n * f, n_harmonics=7)
    theta0 = np.arccos(np.pi * fc / (2 * force))
    h1 = -(1 - 4 * fc / (np.pi * force) * np.exp(-1j * theta0)) / (mass * omega ** 2)
    assert abs(res.H[0] - h1) <= 1e-3 * abs(h1)
    for k in (3, 5, 7):
        h = 4 * fc / (np.pi * mass * omega ** 2 * k ** 3 * force)
        assert abs(res.H[k - 1]) == pytest.approx(h, rel=1e-3)


def test_repeats_mean_std_and_grid_layout():
    rng = np.random.default_rng(0)
    n, p, r = 256, 4, 5
    amps = np.array([0.5, 1.0, 2.0])
    bins = np.array([3, 8])
    t = np.arange(p * n)
    u = amps[:, None, None, None] * np.sin(2 * np.pi * bins[None, :, None, None] * t / n
                                           + rng.uniform(0, 6, (3, 2, r, 1)))
    y = np.tanh(u) + 0.01 * rng.standard_normal(u.shape)
    u = u.reshape(3, 2, r, p, n)
    y = y.reshape(3, 2, r, p, n)
    res = hosidf(u, y, fs=1000.0, n_harmonics=5)
    assert res.H.shape == (3, 2, 5) and res.H_std.shape == (3, 2, 5)
    assert res.H_repeats.shape == (3, 2, r, 5)
    np.testing.assert_allclose(res.f0, np.broadcast_to(bins * 1000.0 / n, (3, 2)))
    np.testing.assert_allclose(res.amplitude, np.broadcast_to(amps[:, None], (3, 2)), rtol=1e-3)
    # tanh: H_1 falls with amplitude, H_3 is negative-real (odd), std from the added noise
    assert np.all(np.diff(np.abs(res.H[:, 0, 0])) < 0)
    assert np.all(res.H[:, :, 2].real < 0)
    expected_std = 0.01 * np.sqrt(2 / (n * p)) / amps      # noise on one line / |U|
    np.testing.assert_allclose(res.H_std[:, 0, 1], expected_std, rtol=0.6)
    one = hosidf(u[:, :, :1], y[:, :, :1], fs=1000.0, n_harmonics=5)
    assert np.all(np.isnan(one.H_std))


def test_sine_off_the_dft_grid_is_rejected():
    n = 512
    t = np.arange(n)
    u = np.sin(2 * np.pi * 10.3 * t / n).reshape(1, 1, n)
    with pytest.raises(InputError, match="off the DFT grid"):
        hosidf(u, u, fs=512.0)
    on = np.sin(2 * np.pi * 10 * t / n).reshape(1, 1, n)
    with pytest.raises(InputError, match="not on a DFT line"):
        hosidf(on, on, fs=512.0, f0=10.3)
    assert hosidf(on, on, fs=512.0, f0=10.0).H[0] == pytest.approx(1.0)
    with pytest.raises(InputError, match="fs/2"):
        hosidf(on, on, fs=512.0, n_harmonics=30)
    # one period per block with DC and a 2nd harmonic in the input: not mistaken for leakage
    one = (0.3 + np.sin(2 * np.pi * t / n) + 0.05 * np.sin(4 * np.pi * t / n)).reshape(1, 1, n)
    assert hosidf(one, one ** 3, fs=512.0, n_harmonics=3).f0 == pytest.approx(1.0)
    bad = on.copy()
    bad[0, 0, 3] = np.inf
    with pytest.raises(InputError, match="NaN or inf"):
        hosidf(on, bad, fs=512.0)
