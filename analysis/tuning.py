"""The friction feed-forward objective and ask/tell searches for K_fc.

Objective (the paper's eq. 6 leaves the combination of odd harmonics open; this is ours):

    r(K_fc) = sqrt(mean_{i in I} |H_i(K_fc)|^2) / |H_1(K_fc)|,   I = {3, 5, 7} by default,

the rms of the selected odd higher harmonics relative to the fundamental, from HOSIDFs
measured with the feed-forward gain K_fc (same sine, same amplitude).

Signed variant: with Coulomb friction Fc and feed forward K_fc, the residual nonlinearity
is a relay of height (Fc - K_fc); its odd HOSIDFs are proportional to (Fc - K_fc) and turn
by 180 deg at K_fc = Fc (paper, Figure 7). With phi_i the phase of H_i measured at
under-compensation (typically K_fc = 0), the projection

    s(K_fc) = mean_{i in I} Re(H_i(K_fc) exp(-j phi_i)) / |H_1(K_fc)|

is positive while under-compensated, negative when over-compensated, and crosses zero at
the optimum, roughly linearly. A root finder on s needs far fewer experiments than a
minimiser on r.

Searches (one experiment per step, the host drives them)::

    search = SignedRootSearch(0.0, k_max, xtol=1e-3)      # or RatioMinimizer(...)
    while not search.done:
        k = search.ask()
        H = measure_hosidf(k)                            # host experiment
        search.tell(k, signed_odd_ratio(H, phases))      # or odd_ratio(H)
    result = search.result                               # TuningResult
"""
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["DEFAULT_HARMONICS", "odd_ratio", "signed_odd_ratio", "signed_odd_ratio_std",
           "reference_phases",
           "TuningResult", "RatioMinimizer", "SignedRootSearch"]

DEFAULT_HARMONICS = (3, 5, 7)


def _harmonic(H, k):
    H = np.asarray(H)
    if H.shape[-1] < k:
        raise InputError(f"tuning: harmonic {k} requested but H holds only "
                         f"{H.shape[-1]} harmonics")
    return H[..., k - 1]


def odd_ratio(H, harmonics=DEFAULT_HARMONICS):
    """r = rms of |H_i|, i in ``harmonics``, over |H_1| (dimensionless).

    Parameters
    ----------
    H : array_like of complex, shape (..., K)
        HOSIDFs H_1 .. H_K (e.g. ``HosidfResult.H``).
    harmonics : sequence of int
        The odd harmonics combined (default 3, 5, 7).

    Returns
    -------
    ndarray or float, shape (...)
    """
    power = np.mean([np.abs(_harmonic(H, k)) ** 2 for k in harmonics], axis=0)
    return np.sqrt(power) / np.abs(_harmonic(H, 1))


def reference_phases(H, harmonics=DEFAULT_HARMONICS):
    """Phases (rad) of H_i, i in ``harmonics``, to use as the under-compensated reference."""
    return np.array([np.angle(_harmonic(H, k)) for k in harmonics])


def signed_odd_ratio(H, phases_rad, harmonics=DEFAULT_HARMONICS):
    """s = mean_i Re(H_i exp(-j phi_i)) / |H_1|: > 0 under-, < 0 over-compensated.

    Parameters
    ----------
    H : array_like of complex, shape (..., K)
    phases_rad : array_like, shape (len(harmonics),)
        Reference phases phi_i, from :func:`reference_phases` of an under-compensated
        measurement (e.g. K_fc = 0).
    harmonics : sequence of int

    Returns
    -------
    ndarray or float, shape (...)
    """
    phases_rad = np.asarray(phases_rad, dtype=float)
    if phases_rad.shape != (len(harmonics),):
        raise InputError(f"tuning: need {len(harmonics)} reference phases, got {phases_rad.shape}")
    proj = [np.real(_harmonic(H, k) * np.exp(-1j * phi)) for k, phi in zip(harmonics, phases_rad)]
    return np.mean(proj, axis=0) / np.abs(_harmonic(H, 1))


def signed_odd_ratio_std(H, H_std, n_repeats, harmonics=DEFAULT_HARMONICS):
    """Standard deviation of :func:`signed_odd_ratio` from the repeat scatter.

    With ``H_std`` the standard deviation of one repeat's complex H_k
    (``HosidfResult.H_std``) and R repeats averaged, each projection has variance
    H_std^2 / (2 R) (half of a circular complex variance); the noise of |H_1| is
    neglected. Use it (times 2 or 3) as ``ftol`` of :class:`SignedRootSearch`.

    Returns
    -------
    ndarray or float, shape (...)
    """
    var = np.mean([_harmonic(H_std, k) ** 2 for k in harmonics], axis=0) / (
        2 * int(n_repeats) * len(harmonics))
    return np.sqrt(var) / np.abs(_harmonic(H, 1))


@dataclass
class TuningResult:
    """Outcome of a K_fc search.

    Attributes
    ----------
    k_fc : float
        Best estimate of K_fc* (feed-forward unit).
    uncertainty : float
        Half-width of the interval known to contain K_fc* (see each search).
    n_evaluations : int
        Experiments used.
    converged : bool
        Stopped by its tolerance (not by ``max_evaluations`` or a failure).
    reason : str
    history : list of (k_fc, value)
    """

    k_fc: float
    uncertainty: float
    n_evaluations: int
    converged: bool
    reason: str
    history: list = field(default_factory=list)


class _AskTell:
    """Runs a search written as a generator (``value = yield k``) one step at a time."""

    def __init__(self, lower, upper, xtol, max_evaluations):
        lower, upper = float(lower), float(upper)
        if not (np.isfinite(lower) and np.isfinite(upper) and lower < upper):
            raise InputError(f"tuning: bracket must satisfy lower < upper, got [{lower}, {upper}]")
        if not xtol > 0:
            raise InputError(f"tuning: xtol must be > 0, got {xtol}")
        if int(max_evaluations) < 3:
            raise InputError("tuning: max_evaluations must be >= 3")
        self.lower, self.upper, self.xtol = lower, upper, float(xtol)
        self.max_evaluations = int(max_evaluations)
        self.history = []
        self._result = None
        self._gen = self._run()
        self._pending = next(self._gen)

    @property
    def done(self):
        """True when the search has stopped (see :attr:`result`)."""
        return self._result is not None

    def ask(self):
        """The K_fc of the next experiment."""
        if self.done:
            raise InputError("tuning: the search is finished; read .result")
        return self._pending

    def tell(self, k_fc, value):
        """Report the objective measured at ``k_fc`` (must be the value just asked)."""
        if self.done:
            raise InputError("tuning: the search is finished; read .result")
        if not np.isclose(k_fc, self._pending, rtol=0, atol=1e-12 * max(1.0, abs(k_fc))):
            raise InputError(f"tuning: told K_fc = {k_fc}, but the search asked {self._pending}")
        value = float(value)
        if not np.isfinite(value):
            raise InputError(f"tuning: objective at K_fc = {k_fc} is not finite ({value})")
        self.history.append((float(self._pending), value))
        if len(self.history) >= self.max_evaluations:
            # let the algorithm see the value, then stop if it did not finish itself
            try:
                self._pending = self._gen.send(value)
            except StopIteration as stop:
                self._result = stop.value
                return
            self._result = self._finish(converged=False, reason="max_evaluations reached")
            return
        try:
            self._pending = self._gen.send(value)
        except StopIteration as stop:
            self._result = stop.value

    @property
    def result(self):
        """:class:`TuningResult` once :attr:`done`, else the current best guess."""
        if self._result is not None:
            return self._result
        return self._finish(converged=False, reason="running")

    def run(self, objective):
        """Drive the search with a callable ``objective(k_fc) -> value`` (tests, offline)."""
        while not self.done:
            k = self.ask()
            self.tell(k, objective(k))
        return self.result


class RatioMinimizer(_AskTell):
    """Brent's minimiser (golden section + parabolic steps) on r(K_fc) over [lower, upper].

    Internally minimises r^2: where the odd harmonics grow linearly with |K_fc - Fc|,
    r^2 is close to a parabola, which Brent's parabolic steps hit in a few
    experiments (r itself has a V-shaped minimum that only golden steps can shrink).
    The endpoints are not evaluated.

    Parameters
    ----------
    lower, upper : float
        Bracket [0, K_max] (feed-forward unit).
    xtol : float
        Stop when the bracket around the minimum is about 4 xtol wide.
    max_evaluations : int

    Notes
    -----
    ``uncertainty`` is half the final bracket (the minimiser of a unimodal r lies in it).
    """

    def __init__(self, lower, upper, xtol=None, max_evaluations=20):
        xtol = (float(upper) - float(lower)) * 1e-3 if xtol is None else xtol
        super().__init__(lower, upper, xtol, max_evaluations)

    def _finish(self, converged, reason):
        best = min(self.history, key=lambda kv: kv[1]) if self.history else (
            (self.lower + self.upper) / 2, np.nan)
        return TuningResult(k_fc=best[0], uncertainty=(self._b - self._a) / 2,
                            n_evaluations=len(self.history), converged=converged,
                            reason=reason, history=list(self.history))

    def _run(self):
        # Brent (1973) "fmin", as in Forsythe, Malcolm and Moler, on f = r^2
        golden = (3 - np.sqrt(5)) / 2
        eps = np.sqrt(np.finfo(float).eps)
        a, b = self.lower, self.upper
        self._a, self._b = a, b
        x = w = v = a + golden * (b - a)
        fx = (yield x) ** 2
        fw = fv = fx
        d = e = 0.0
        while True:
            xm = 0.5 * (a + b)
            tol1 = eps * abs(x) + self.xtol / 3
            tol2 = 2 * tol1
            if abs(x - xm) <= tol2 - 0.5 * (b - a):
                return self._finish(True, f"bracket below {4 * tol1:.3g}")
            use_golden = True
            if abs(e) > tol1:
                r = (x - w) * (fx - fv)
                q = (x - v) * (fx - fw)
                p = (x - v) * q - (x - w) * r
                q = 2 * (q - r)
                if q > 0:
                    p = -p
                q = abs(q)
                e_prev, e = e, d
                if abs(p) < abs(0.5 * q * e_prev) and q * (a - x) < p < q * (b - x):
                    d = p / q
                    u = x + d
                    if (u - a) < tol2 or (b - u) < tol2:
                        d = tol1 if xm >= x else -tol1
                    use_golden = False
            if use_golden:
                e = (a - x) if x >= xm else (b - x)
                d = golden * e
            u = x + (d if abs(d) >= tol1 else (tol1 if d >= 0 else -tol1))
            fu = (yield u) ** 2
            if fu <= fx:
                if u >= x:
                    a = x
                else:
                    b = x
                v, fv, w, fw, x, fx = w, fw, x, fx, u, fu
            else:
                if u < x:
                    a = u
                else:
                    b = u
                if fu <= fw or w == x:
                    v, fv, w, fw = w, fw, u, fu
                elif fu <= fv or v == x or v == w:
                    v, fv = u, fu
            self._a, self._b = a, b


class SignedRootSearch(_AskTell):
    """Illinois (modified regula falsi) root search on the signed objective s(K_fc).

    The first two experiments are the bracket ends (s > 0 at ``lower``, under-compensated;
    s < 0 at ``upper``); then secant steps that keep the sign change bracketed, halving
    the retained end's value when the same end is kept twice (Illinois), which keeps
    superlinear convergence. A linear s is solved on the third experiment.

    Parameters
    ----------
    lower, upper : float
        Bracket [0, K_max].
    xtol : float
        Stop when successive estimates (or the bracket) agree within xtol.
    ftol : float
        Stop when |s| <= ftol (set it to the noise level of s on measured data).
    max_evaluations : int

    Notes
    -----
    ``uncertainty`` is min(half the sign-change bracket, the last step |k_n - k_{n-1}|).
    Without a sign change in the bracket the search stops, unconverged, at the end with
    the smaller |s| (K_fc* is outside [lower, upper]).
    """

    def __init__(self, lower, upper, xtol=None, ftol=0.0, max_evaluations=12):
        xtol = (float(upper) - float(lower)) * 1e-4 if xtol is None else xtol
        self.ftol = float(ftol)
        super().__init__(lower, upper, xtol, max_evaluations)

    def _finish(self, converged, reason):
        if not self.history:
            return TuningResult((self.lower + self.upper) / 2, (self.upper - self.lower) / 2,
                                0, False, reason, [])
        if len(self.history) >= 3:
            k_best = self.history[-1][0]
            step = abs(self.history[-1][0] - self.history[-2][0])
        else:
            k_best = min(self.history, key=lambda kv: abs(kv[1]))[0]
            step = np.inf
        half = (self._b - self._a) / 2 if self._bracketed else np.inf
        unc = min(half, step)
        if not np.isfinite(unc):
            unc = (self.upper - self.lower) / 2
        return TuningResult(k_fc=k_best, uncertainty=unc, n_evaluations=len(self.history),
                            converged=converged, reason=reason, history=list(self.history))

    def _run(self):
        self._bracketed = False
        a, b = self.lower, self.upper
        self._a, self._b = a, b
        fa = yield a
        if fa == 0:
            return self._finish_at(a, "s = 0 at the lower end")
        fb = yield b
        if fb == 0:
            return self._finish_at(b, "s = 0 at the upper end")
        if np.sign(fa) == np.sign(fb):
            end = a if abs(fa) < abs(fb) else b
            res = self._finish(False, "no sign change of s in the bracket: K_fc* lies outside "
                                      f"[{a:g}, {b:g}]")
            res.k_fc = end
            return res
        self._bracketed = True
        side = 0
        c_prev = None
        while True:
            c = (a * fb - b * fa) / (fb - fa)
            fc = yield c
            if abs(fc) <= self.ftol:
                self._a = self._b = c
                return self._finish(True, f"|s| <= ftol = {self.ftol:g}")
            if np.sign(fc) == np.sign(fb):
                b, fb = c, fc
                if side == -1:
                    fa /= 2
                side = -1
            else:
                a, fa = c, fc
                if side == +1:
                    fb /= 2
                side = +1
            self._a, self._b = min(a, b), max(a, b)
            if abs(b - a) <= 2 * self.xtol:
                return self._finish(True, "bracket below 2 xtol")
            if c_prev is not None and abs(c - c_prev) <= self.xtol:
                return self._finish(True, "step below xtol")
            c_prev = c

    def _finish_at(self, k, reason):
        res = self._finish(True, reason)
        res.k_fc, res.uncertainty = k, 0.0
        return res
