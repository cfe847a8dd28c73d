"""The whole friction feed-forward at once: a model-based tune of several terms (issue 35).

The drive's feed-forward (firmware_sim/core/ctl.h, objects 0x2000:4, 5, 9, 10, 11)::

    FF = sgn(v_r) (K_fc + K_ps sin(theta_r) + K_pc cos(theta_r)) + K_fa |sgn(v_r)| + K_v v_r

Terms (``tune.terms``), each in the units of the drive output:

=========== ============================================ =========== ==================
term        meaning                                      unit        drive object
=========== ============================================ =========== ==================
coulomb     mean of the two directions' levels Fc+, Fc-  V           0x2000:4  K_fc
asymmetry   half their difference (Fc+ - Fc-) / 2        V           0x2000:9  K_fa
viscous     velocity-proportional friction               V s/rad     0x2000:5  K_v
position    amplitude of the level's first harmonic      V           0x2000:10 K_ps,
            over one revolution                                      0x2000:11 K_pc
=========== ============================================ =========== ==================

The estimate. In periodic steady state of a sine experiment the plant input u and the
motor angle y obey, at every harmonic k of the sine (lines X_k, X_0 the mean),

    U_k = Z(k w) Y_k + sum_i theta_i Psi_i(k),     Z(s) = J' s^2 + b' s   (rigid body, per V)

with Psi_i the lines of the terms' regressors along the motion (sgn(v), |sgn(v)|,
sin(y) sgn(v), cos(y) sgn(v); v the velocity), theta_i the friction's own values and b' the
viscous term. The loop's process sensitivity PS = 1 / (Z + C) (C the controller) is this
Z seen from the drive output: knowing Z is knowing PS, and the output harmonics the
feed-forward leaves, Y_k = PS(k w) (FF_k - F_k), vanish when FF matches the friction F along
the motion. One experiment gives all terms (and J', b') at once by linear least squares
over k = 0 .. n_fit: a Gauss-Newton step whose Jacobian is exact in the gains. The motion
is modelled by its mean and fundamental (y0 + Re(Y_1 e^(j w t)), its velocity's sign):
robust against encoder steps and noise, exact while the motor slides. The motion depends
on the gains (stick-slip without feed-forward), so the step is iterated: the first
experiment without feed-forward, the next at the estimate, until the estimate moves less
than ``rtol``; then one experiment at half the amplitude with the final gains (its estimate
measures what changes with the amplitude and with the gains: the ``amplitude`` part of
sigma), and, when a verification amplitude is configured, one there (the odd and even
levels at the optimum).

Sigma per term: the noise (spread of the per-period estimates over the recorded periods,
or the fit's residual when only the mean lines are told) and the amplitude / linearisation
part, in quadrature. A term with sigma above ``max_sigma_re_coulomb`` of the Coulomb level
ends the tune unconverged with the reason.

Ask/tell (the host executes, the object decides)::

    tuner = FeedForwardModelTune(["coulomb", "viscous"], omega_rad_s=w, n_period=4096,
                                 cycles=1, amplitude_rad=1.0)
    while not tuner.done:
        exp = tuner.ask()                      # Experiment: amplitude, gains (drive aliases)
        U, Y = measure(exp)                    # lines k = 0 .. K per period, (P, K + 1)
        tuner.tell(exp, U, Y)
    tuner.result                               # dict: terms, experiments, ratios ...

:meth:`FeedForwardModelTune.replay` runs the same decisions from recorded lines.
"""
import math
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["TERMS", "TERM_INFO", "Experiment", "harmonic_lines", "motion_regressors", "process_sensitivity",
           "gauss_newton_step",
           "estimate_terms", "odd_even_ratios", "FeedForwardModelTune"]

TERMS = ("coulomb", "asymmetry", "viscous", "position")
# unit, drive object(s), drive gain alias(es)
TERM_INFO = {
    "coulomb": ("V", "0x2000:4", ("kfc",)),
    "asymmetry": ("V", "0x2000:9", ("kfa",)),
    "viscous": ("V s/rad", "0x2000:5", ("kv",)),
    "position": ("V", "0x2000:10 (sine), 0x2000:11 (cosine)", ("kps", "kpc")),
}
GAINS = ("kfc", "kfa", "kv", "kps", "kpc")
# the drive's limits (configs/od.yaml 0x2000): K_fc, K_v in [0, 100], the signed ones +-100
GAIN_LIMITS = {"kfc": (0.0, 100.0), "kv": (0.0, 100.0), "kfa": (-100.0, 100.0),
               "kps": (-100.0, 100.0), "kpc": (-100.0, 100.0)}
# regressor columns of each term (the position term has two: sine and cosine)
_COLUMNS = {"coulomb": ("kfc",), "asymmetry": ("kfa",), "position": ("kps", "kpc")}


def harmonic_lines(x, n_period, cycles, n_harmonics):
    """Lines k = 0 .. n_harmonics of each period of ``x``.

    Parameters
    ----------
    x : array_like, shape (P * n_period,)
        Whole periods of a periodic signal.
    n_period : int
        Samples per period.
    cycles : int
        Sine cycles per period (line k sits at DFT bin k * cycles).
    n_harmonics : int

    Returns
    -------
    X : ndarray, complex, shape (P, n_harmonics + 1)
        X_0 the period's mean, X_k = (2 / N) DFT(k cycles), so that a period is
        X_0 + sum_k Re(X_k exp(j k w t)).
    """
    x = np.asarray(x, dtype=float)
    if n_period < 4 or x.size < n_period or x.size % n_period:
        raise InputError(f"harmonic_lines: {x.size} samples are not whole periods of {n_period}")
    if (n_harmonics + 1) * cycles * 2 > n_period:
        raise InputError(f"harmonic_lines: harmonic {n_harmonics} of {cycles} cycles is above N/2 = {n_period // 2}")
    F = np.fft.rfft(x.reshape(-1, n_period), axis=1) / n_period
    bins = cycles * np.arange(n_harmonics + 1)
    X = 2.0 * F[:, bins]
    X[:, 0] = F[:, 0].real
    return X


def _lines_of(sig, cycles, n_harmonics):
    n = sig.shape[-1]
    F = np.fft.rfft(sig, axis=-1) / n
    X = 2.0 * F[..., cycles * np.arange(n_harmonics + 1)]
    X[..., 0] = F[..., 0].real
    return X


def motion_regressors(y0_rad, y1, cycles, n_harmonics, n_grid=4096):
    """Lines k = 0 .. n_harmonics of the friction regressors along the motion
    y(t) = y0 + Re(Y_1 exp(j w t)) (its mean and fundamental).

    Returns
    -------
    dict
        ``kfc``: sgn(v), ``kfa``: |sgn(v)|, ``kps``: sin(y) sgn(v), ``kpc``: cos(y) sgn(v),
        each a complex array of n_harmonics + 1 lines (the drive gain's regressor).
    """
    t = np.arange(n_grid) / n_grid * cycles * 2 * np.pi    # w t over one period
    e = np.exp(1j * t)
    y = y0_rad + (y1 * e).real
    sg = np.sign((1j * y1 * e).real)
    regs = {"kfc": sg, "kfa": np.abs(sg), "kps": np.sin(y) * sg, "kpc": np.cos(y) * sg}
    return {k: _lines_of(v, cycles, n_harmonics) for k, v in regs.items()}


def _design(U, Y, omega_rad_s, terms, n_fit, cycles):
    """Real least-squares system of one period's (or the mean) lines."""
    ks = np.arange(n_fit + 1)
    regs = motion_regressors(float(np.real(Y[0])), complex(Y[1]), 1, n_fit)
    cols, names = [], []
    for term in terms:
        for g in _COLUMNS.get(term, ()):
            cols.append(regs[g])
            names.append(g)
    kw = ks * omega_rad_s
    cols.append(-(kw ** 2) * Y[:n_fit + 1])
    names.append("inertia")
    cols.append(1j * kw * Y[:n_fit + 1])
    names.append("kv")
    A = np.array(cols).T
    b = np.asarray(U[:n_fit + 1])
    # k = 0: the real part only (the mean has no imaginary part)
    Ar = np.vstack([A.real, A.imag[1:]])
    br = np.concatenate([b.real, b.imag[1:]])
    return Ar, br, names


def estimate_terms(U, Y, *, omega_rad_s, terms, n_fit=5, cycles=1, line_var=None, n_periods=None):
    """Friction terms, inertia and viscous term from the lines of one experiment.

    Parameters
    ----------
    U, Y : array_like, complex, shape (K + 1,) or (P, K + 1)
        Lines k = 0 .. K (:func:`harmonic_lines`) of the plant input [V] and the motor angle
        [rad, absolute: the position term needs it], the mean or per period.
    omega_rad_s : float
        The sine's angular frequency.
    terms : sequence of str
        Subset of :data:`TERMS`; the inertia and the viscous term are always in the model
        (the viscous term is the rigid body's damping).
    n_fit : int
        Highest harmonic in the fit (K >= n_fit).
    line_var : array_like or None
        With mean lines only (a drive's statistics): the period-to-period variance
        E|X_p - X|^2 of the plant input's lines k = 0 .. K, and ``n_periods`` P; the noise is
        then propagated from it instead of taken from the fit's residual (which also holds
        the model's misfit).

    Returns
    -------
    dict
        ``values``: {gain alias or 'inertia': value} from the mean lines; ``noise``: the
        standard error of each (over the periods when P >= 2, else from the residual);
        ``residual_rel``: rms residual over rms(U) of the fit.
    """
    U = np.atleast_2d(np.asarray(U, dtype=complex))
    Y = np.atleast_2d(np.asarray(Y, dtype=complex))
    if U.shape != Y.shape or U.shape[1] < n_fit + 1 or n_fit < 3:
        raise InputError(f"estimate_terms: U {U.shape} and Y {Y.shape} need the same shape with at least "
                         f"n_fit + 1 = {n_fit + 1} lines (n_fit >= 3)")
    bad = [t for t in terms if t not in TERMS]
    if bad:
        raise InputError(f"estimate_terms: unknown term(s) {bad}; known: {list(TERMS)}")
    if not (np.all(np.isfinite(U)) and np.all(np.isfinite(Y))):
        raise InputError("estimate_terms: the lines are not all finite")
    if abs(Y[:, 1]).min() <= 0:
        raise InputError("estimate_terms: no fundamental in the motion (the motor did not move)")
    A, b, names = _design(U.mean(axis=0), Y.mean(axis=0), omega_rad_s, terms, n_fit, cycles)
    theta, *_ = np.linalg.lstsq(A, b, rcond=None)
    res = b - A @ theta
    dof = max(A.shape[0] - A.shape[1], 1)
    cov = float(res @ res) / dof * np.linalg.pinv(A.T @ A)
    noise = np.sqrt(np.maximum(np.diag(cov), 0.0))
    P = U.shape[0]
    if P == 1 and line_var is not None and n_periods and n_periods >= 2:
        v = np.asarray(line_var, dtype=float)[:n_fit + 1] / n_periods
        v = np.where(np.isfinite(v), v, np.nanmax(v[1:]) if np.any(np.isfinite(v[1:])) else 0.0)
        w = np.concatenate([v, v[1:]]) / 2.0           # re and im of k >= 1 each half
        w[0] = v[0]
        Ainv = np.linalg.pinv(A)
        noise = np.sqrt(np.maximum(np.einsum("ij,j,ij->i", Ainv, w, Ainv), 0.0))
    if P >= 2:
        per = []
        for p in range(P):
            Ap, bp, _ = _design(U[p], Y[p], omega_rad_s, terms, n_fit, cycles)
            per.append(np.linalg.lstsq(Ap, bp, rcond=None)[0])
        noise = np.std(np.array(per), axis=0, ddof=1) / math.sqrt(P)
    rel = float(np.sqrt(np.mean(res ** 2)) / max(np.sqrt(np.mean(b ** 2)), 1e-300))
    return {"values": dict(zip(names, (float(v) for v in theta))),
            "noise": dict(zip(names, (float(v) for v in noise))),
            "residual_rel": rel}


def odd_even_ratios(Y, odd=(3, 5, 7), even=(2, 4, 6)):
    """(odd, even): rms of |Y_k| over ``odd`` and over ``even``, relative to |Y_1|
    (= rms of |H_k| / |H_1|, the HOSIDFs of one sine). ``Y``: lines k = 0 .. K (or per
    period: averaged first)."""
    Y = np.asarray(Y, dtype=complex)
    if Y.ndim == 2:
        Y = Y.mean(axis=0)
    if Y.size <= max(max(odd), max(even)):
        raise InputError(f"odd_even_ratios: {Y.size} lines, harmonic {max(max(odd), max(even))} needed")
    y1 = abs(Y[1])
    if not y1 > 0:
        return math.inf, math.inf
    return (float(np.sqrt(np.mean(np.abs(Y[list(odd)]) ** 2)) / y1),
            float(np.sqrt(np.mean(np.abs(Y[list(even)]) ** 2)) / y1))


def process_sensitivity(inertia, viscous, controller, omega_rad_s, orders):
    """PS(k w) = 1 / (Z + C) from the drive output to the angle at the harmonics ``orders``:
    Z = J' s^2 + b' s the fitted rigid body (per V), C = Kp + Kd s / (tau_d s + 1) the
    controller (``controller``: dict kp, kd, tau_d)."""
    s = 1j * omega_rad_s * np.asarray(orders, dtype=float)
    C = controller["kp"] + controller["kd"] * s / (controller.get("tau_d", 0.0) * s + 1.0)
    return 1.0 / (inertia * s ** 2 + viscous * s + C)


def gauss_newton_step(Y, reference_mean_rad, gains_terms, inertia, viscous, controller, omega_rad_s,
                      orders=(2, 3, 4, 5, 6, 7)):
    """The change of the gains that would cancel what one experiment's output lines still
    show: the feed-forward enters at the plant input, so at harmonic k the angle moves by
    PS(k w) Phi_i(k) d_i (Phi_i the lines of gain i's regressor along the motion); the least
    squares over the harmonics ``orders`` (and the mean, where the reference's mean is known:
    PS(0) = 1 / Kp) give d. Returns {gain: d} with the gains in ``gains_terms`` (the viscous
    term acts on the fundamental only, where the linear response also sits: not in it)."""
    Y = np.asarray(Y, dtype=complex)
    if Y.ndim == 2:
        Y = Y.mean(axis=0)
    kmax = max(orders)
    regs = motion_regressors(float(Y[0].real), complex(Y[1]), 1, kmax)
    cols = [g for g in gains_terms if g != "kv"]
    if not cols:
        return {}
    ps = process_sensitivity(inertia, viscous, controller, omega_rad_s, orders)
    A = np.array([ps * regs[g][list(orders)] for g in cols]).T
    b = Y[list(orders)]
    Ar, br = np.vstack([A.real, A.imag]), np.concatenate([b.real, b.imag])
    if reference_mean_rad is not None:
        ps0 = 1.0 / controller["kp"]
        Ar = np.vstack([Ar, [ps0 * regs[g][0].real for g in cols]])
        br = np.concatenate([br, [Y[0].real - reference_mean_rad]])
    d, *_ = np.linalg.lstsq(Ar, br, rcond=None)
    # Y = PS (FF - F): d is the excess of the gains over the friction
    return dict(zip(cols, (float(x) for x in d)))


@dataclass
class Experiment:
    """One closed-loop sine experiment the tune asks for."""
    index: int
    tag: str                 # 'identify', 'amplitude' or 'verify'
    amplitude_rad: float     # sine peak at the reference
    gains: dict              # drive alias -> value (kfc, kfa, kv, kps, kpc)
    estimate: dict = field(default=None)   # what it told (estimate_terms' dict)
    ratios: tuple = field(default=None)    # (odd, even) at this experiment
    lines: tuple = field(default=None)     # (Y lines, reference mean or None) told


class FeedForwardModelTune:
    """Ask/tell model-based tune of the friction feed-forward terms (module docstring).

    Parameters
    ----------
    terms : sequence of str
        Subset of :data:`TERMS` (at least one).
    omega_rad_s : float
        Angular frequency of the sine.
    amplitude_rad : float
        Identification amplitude (peak; with the position term it should sweep a large part
        of the revolution: the level's variation is told apart from the Coulomb level by it).
    verify_amplitude_rad : float or None
        An extra verifying experiment at this amplitude with the final gains (the odd and
        even levels at the optimum); None: the half-amplitude experiment verifies.
    n_fit : int
        Highest harmonic in the fit.
    rtol : float
        Convergence: every gain's step below rtol times the Coulomb scale (the largest of the
        Coulomb estimate and 1e-3 V).
    max_experiments : int
    max_sigma_re_coulomb : float
        A sigma above this share of the Coulomb scale ends the tune unconverged.
    k_fc_max, k_v_max : float
        Upper limits of the gains asked for.
    gain_limits : dict or None
        (low, high) of the signed gains ``kfa``, ``kps``, ``kpc`` asked for (the drive's
        ranges and its output limit); default :data:`GAIN_LIMITS` (configs/od.yaml's +-100 V).
    odd_max : float
        Odd level (rms of |H_3,5,7| / |H_1|) above which an identification experiment at the
        estimate says the model does not hold at its amplitude (stick-slip, Stribeck): the
        next one is at twice the amplitude, up to ``amplitude_max_rad`` (default 8 x the
        first).
    controller : dict or None
        kp, kd, tau_d of the drive's position controller: with it, the Gauss-Newton step of
        :func:`gauss_newton_step` at the half-amplitude experiment (at the final gains: what
        its harmonics still ask to change) is a part of each term's sigma (``linearisation``).
    """

    def __init__(self, terms, *, omega_rad_s, amplitude_rad, verify_amplitude_rad=None, n_fit=5,
                 rtol=0.05, max_experiments=6, max_sigma_re_coulomb=0.1, k_fc_max=100.0, k_v_max=100.0,
                 controller=None, odd_max=0.01, amplitude_max_rad=None, gain_limits=None):
        terms = list(terms)
        bad = [t for t in terms if t not in TERMS]
        if not terms or bad or len(set(terms)) != len(terms):
            raise InputError(f"FeedForwardModelTune: terms {terms}: a non-empty subset of {list(TERMS)} "
                             f"without repeats")
        if not (omega_rad_s > 0 and amplitude_rad > 0):
            raise InputError("FeedForwardModelTune: omega_rad_s and amplitude_rad must be > 0")
        if verify_amplitude_rad is not None and not verify_amplitude_rad > 0:
            raise InputError("FeedForwardModelTune: verify_amplitude_rad must be > 0")
        if max_experiments < 3:
            raise InputError("FeedForwardModelTune: max_experiments must be >= 3")
        self.terms = [t for t in TERMS if t in terms]
        self.omega = float(omega_rad_s)
        self.amplitude = float(amplitude_rad)
        self.amplitude2 = 0.5 * self.amplitude
        self.odd_max = float(odd_max)
        self.amplitude_max = float(amplitude_max_rad) if amplitude_max_rad is not None else 8.0 * self.amplitude
        va = verify_amplitude_rad
        self.verify_amplitude = None if va is None or abs(va - self.amplitude2) <= 1e-9 * va else float(va)
        self.n_fit = int(n_fit)
        self.rtol = float(rtol)
        self.max_experiments = int(max_experiments)
        self.max_sigma = float(max_sigma_re_coulomb)
        signed = dict(gain_limits or {})
        if set(signed) - {"kfa", "kps", "kpc"} or any(not lo <= 0.0 <= hi for lo, hi in signed.values()):
            raise InputError(f"FeedForwardModelTune: gain_limits {signed}: (low <= 0 <= high) of kfa, kps, kpc")
        self.limits = dict(GAIN_LIMITS, **{k: (float(lo), float(hi)) for k, (lo, hi) in signed.items()},
                           kfc=(0.0, float(k_fc_max)), kv=(0.0, float(k_v_max)))
        if controller is not None and not (controller.get("kp", 0) > 0):
            raise InputError("FeedForwardModelTune: controller needs kp > 0")
        self.controller = controller
        self.experiments = []
        self._pending = None
        self._stop = None          # (cause, text) of a failed experiment
        self._result = None

    # ---- ask / tell ----
    @property
    def done(self):
        return self._result is not None

    def ask(self):
        """The next :class:`Experiment`, or None when done."""
        if self.done:
            return None
        if self._pending is None:
            self._pending = self._next()
            if self._pending is None:
                self._finish()
                return None
        return self._pending

    def tell(self, experiment, U, Y, reference_mean_rad=None, line_var=None, n_periods=None):
        """Lines k = 0 .. K (K >= max(n_fit, 7)) of the plant input and the motor angle of
        ``experiment``: (K + 1,) means or (P, K + 1) per period; the reference's mean (the
        set-point) if known (the Gauss-Newton check then uses the mean too); with mean lines,
        the plant input's line variances over ``n_periods`` periods (:func:`estimate_terms`)."""
        if experiment is not self._pending:
            raise InputError("FeedForwardModelTune.tell: not the experiment asked for")
        U = np.asarray(U, dtype=complex)
        Y = np.asarray(Y, dtype=complex)
        if U.shape[-1] < 8:
            raise InputError(f"FeedForwardModelTune.tell: {U.shape[-1]} lines, 8 (k = 0 .. 7) needed")
        experiment.estimate = estimate_terms(U, Y, omega_rad_s=self.omega, terms=self.terms, n_fit=self.n_fit,
                                             line_var=line_var, n_periods=n_periods)
        experiment.ratios = odd_even_ratios(Y)
        experiment.lines = (Y, reference_mean_rad)
        self.experiments.append(experiment)
        self._pending = self._next()      # decided once (the decision may double the amplitude)
        if self._pending is None:
            self._finish()

    def fail(self, experiment, cause, text):
        """The experiment could not be used (saturation, no motion ...): the tune ends
        unconverged with ``cause``."""
        self.experiments.append(experiment)
        self._pending = None
        self._stop = (cause, text)
        self._finish()

    @property
    def result(self):
        return self._result

    @classmethod
    def replay(cls, captures, **kwargs):
        """Run the tune's decisions from recorded lines: ``captures`` a sequence of
        (amplitude_rad, gains, U, Y) in the order measured. Raises InputError when the
        recorded experiments differ from what the tune asks for."""
        tuner = cls(**kwargs)
        for amplitude, gains, U, Y in captures:
            exp = tuner.ask()
            if exp is None:
                raise InputError("replay: more captures than the tune asks for")
            if abs(exp.amplitude_rad - amplitude) > 1e-9 * amplitude or \
                    any(abs(exp.gains[g] - gains.get(g, 0.0)) > 1e-6 * max(1.0, abs(exp.gains[g])) for g in GAINS):
                raise InputError(f"replay: capture {exp.index} was measured at amplitude {amplitude:g} rad, "
                                 f"gains {gains}; the tune asks for {exp.amplitude_rad:g} rad, {exp.gains}")
            tuner.tell(exp, U, Y)
        if not tuner.done:
            raise InputError(f"replay: {len(captures)} captures, the tune asks for more")
        return tuner

    # ---- strategy ----
    def _gains_from(self, est):
        v = est["values"]
        g = {k: 0.0 for k in GAINS}
        # the viscous feed-forward always: it removes the lag the viscous friction gives the
        # motion, so the friction (acting along the motion) and the feed-forward (along the
        # reference) switch together; without it the Coulomb estimate comes out 2-4 % low
        # (configs/plant_twomass.yaml with viscous 2e-3 N m s/rad at 1 rad)
        g["kv"] = v["kv"]
        for term in self.terms:
            for alias in TERM_INFO[term][2]:
                g[alias] = v[alias]
        for k, (lo, hi) in self.limits.items():
            g[k] = float(min(max(g[k], lo), hi))
        return g

    def _scale(self, est):
        return max(abs(est["values"].get("kfc", 0.0)), 1e-3)

    def _identify(self):
        return [e for e in self.experiments if e.tag == "identify"]

    def _next(self):
        if self._stop is not None:
            return None
        n = len(self.experiments)
        ident = self._identify()
        zero = {k: 0.0 for k in GAINS}
        if not ident:
            return Experiment(n, "identify", self.amplitude, zero)
        last = ident[-1]
        g_next = self._gains_from(last.estimate)
        has_amp = any(e.tag == "amplitude" for e in self.experiments)
        has_ver = any(e.tag == "verify" for e in self.experiments)
        if not has_amp:
            room = self.max_experiments - n - 1 - (self.verify_amplitude is not None)
            # with the feed-forward at the estimate the odd harmonics should be gone while the
            # motor slides; more than odd_max of them: stick-slip or a Stribeck curve the model
            # does not have at this amplitude: twice the amplitude (the estimate carried on)
            if len(ident) >= 2 and last.ratios[0] > self.odd_max and room > 1 and \
                    2 * self.amplitude <= self.amplitude_max:
                self.amplitude *= 2
                self.amplitude2 = 0.5 * self.amplitude
                return Experiment(n, "identify", self.amplitude, g_next)
            same = [e for e in ident if e.amplitude_rad == self.amplitude]
            step = max(abs(g_next[k] - last.gains[k]) for k in GAINS)
            converged = len(ident) >= 2 and step <= self.rtol * self._scale(last.estimate)
            if not same or (not converged and room > 0):
                return Experiment(n, "identify", self.amplitude, g_next)
            return Experiment(n, "amplitude", self.amplitude2, g_next)
        if self.verify_amplitude is not None and not has_ver:
            amp = [e for e in self.experiments if e.tag == "amplitude"][-1]
            return Experiment(n, "verify", self.verify_amplitude, dict(amp.gains))
        return None

    def _finish(self):
        ident = self._identify()
        amp = [e for e in self.experiments if e.tag == "amplitude" and e.estimate is not None]
        ver = [e for e in self.experiments if e.tag == "verify" and e.estimate is not None]
        res = {"method": "model", "terms_requested": list(self.terms), "experiments": len(self.experiments),
               "converged": False, "reason": None, "cause": None, "terms": {}, "gains": None,
               "odd_ratio_at_optimum": None, "even_ratio_at_optimum": None,
               "odd_ratio_at_start": None, "even_ratio_at_start": None, "inertia_v_s2_per_rad": None,
               "verification": None,
               "iterations": [{"tag": e.tag, "amplitude_rad": e.amplitude_rad, "gains": dict(e.gains),
                               "estimate": None if e.estimate is None else dict(e.estimate["values"]),
                               "fit_residual_rel": None if e.estimate is None else e.estimate["residual_rel"],
                               "odd_ratio": None if e.ratios is None else e.ratios[0],
                               "even_ratio": None if e.ratios is None else e.ratios[1]}
                              for e in self.experiments]}
        if ident and ident[0].ratios is not None:
            res["odd_ratio_at_start"], res["even_ratio_at_start"] = ident[0].ratios
        if self._stop is not None:
            res["cause"], res["reason"] = self._stop[0], f"{self._stop[0]}: {self._stop[1]}"
            self._result = res
            return
        final = ident[-1]
        v = final.estimate["values"]
        noise = final.estimate["noise"]
        v2 = amp[-1].estimate["values"] if amp else None
        gains = self._gains_from(final.estimate)
        res["gains"] = gains
        res["inertia_v_s2_per_rad"] = v["inertia"]
        scale = self._scale(final.estimate)
        verifier = ver[-1] if ver else (amp[-1] if amp else final)
        gn = {}
        if self.controller is not None:
            aliases = [a for t in self.terms for a in TERM_INFO[t][2]]
            # at the half-amplitude experiment (the final gains, a wide sweep: a small
            # verification amplitude cannot tell the position term from the Coulomb level)
            chk = amp[-1] if amp else final
            gn = gauss_newton_step(chk.lines[0], chk.lines[1], aliases, v["inertia"], v["kv"],
                                   self.controller, self.omega)
        res["gauss_newton_step"] = gn or None
        worst = None
        for term in self.terms:
            unit, obj, aliases = TERM_INFO[term]
            if term == "position":
                ps, pc = v["kps"], v["kpc"]
                value = math.hypot(ps, pc)
                n_ps, n_pc = noise["kps"], noise["kpc"]
                s_noise = math.hypot(ps * n_ps, pc * n_pc) / value if value > 0 else math.hypot(n_ps, n_pc)
                s_amp = abs(math.hypot(v2["kps"], v2["kpc"]) - value) if v2 else math.nan
                s_gn = math.hypot(gn["kps"], gn["kpc"]) if gn else math.nan
                extra = {"sine_v": ps, "cosine_v": pc, "phase_deg": math.degrees(math.atan2(pc, ps))}
            else:
                a = aliases[0]
                value, s_noise = v[a], noise[a]
                s_amp = abs(v2[a] - value) if v2 else math.nan
                s_gn = abs(gn[a]) if a in gn else math.nan
                extra = {}
            parts = {"noise": s_noise, "amplitude": s_amp, "linearisation": s_gn}
            sigma = math.sqrt(sum(x * x for x in parts.values() if math.isfinite(x)))
            res["terms"][term] = {"value": value, "sigma": sigma, "unit": unit, "object": obj,
                                  "parts": parts, **extra}
            if term != "viscous" and sigma > self.max_sigma * scale and (worst is None or sigma > worst[1]):
                worst = (term, sigma)
        if "coulomb" in res["terms"]:
            c = res["terms"]["coulomb"]
            if "asymmetry" in res["terms"]:
                a = res["terms"]["asymmetry"]
                s = math.hypot(c["sigma"], a["sigma"])
                res["terms"]["coulomb"]["fc_plus_v"] = c["value"] + a["value"]
                res["terms"]["coulomb"]["fc_minus_v"] = c["value"] - a["value"]
                res["terms"]["coulomb"]["fc_plus_minus_sigma_v"] = s
        res["odd_ratio_at_optimum"], res["even_ratio_at_optimum"] = verifier.ratios
        res["verification"] = {"tag": verifier.tag, "amplitude_rad": verifier.amplitude_rad,
                               "gains": dict(verifier.gains)}
        if final.ratios[0] > self.odd_max and len(ident) >= 2:
            res["reason"] = (f"the odd harmonics at the estimate are {100 * final.ratios[0]:.2g} % of the "
                             f"fundamental at {final.amplitude_rad:g} rad (more than {100 * self.odd_max:g} %): "
                             f"the friction is not the modelled one there (stick-slip, a Stribeck curve); "
                             f"raise tune.model.amplitude_rad or tune.amplitude_max_rad")
            res["cause"] = "model"
        elif worst is not None:
            res["reason"] = (f"cannot tell the {worst[0]} term better than +-{100 * worst[1] / scale:.3g} % of "
                             f"the Coulomb level (more than {100 * self.max_sigma:g} %)")
            res["cause"] = "uncertain"
        else:
            res["converged"] = True
            res["reason"] = (f"{len(ident)} identification experiment(s) at {self.amplitude:g} rad, one at "
                             f"{self.amplitude2:g} rad" + (f", verified at {self.verify_amplitude:g} rad"
                                                          if self.verify_amplitude else ""))
        self._result = res
