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
           "TuningResult", "RatioMinimizer", "SignedRootSearch",
           "ODD_LEVEL_DEFINITION", "harmonic_orders", "SearchPoint", "KfcSearchResult", "KfcSearch",
           "loop_lag_part", "smoothed_sign_bias", "halved_frequency", "drift_between", "STOP_CAUSES", "PART_CAUSES"]

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


class _GeneratorSearch:
    """Ask/tell plumbing of a search written as a generator (``told = yield k``).

    Subclasses define ``_run()`` (the generator, returning the result) and ``result``;
    ``tell`` checks the K_fc against the one asked (:meth:`_check_told`) and hands the
    measurement on with :meth:`_advance`.
    """

    def _start(self):
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

    def _check_told(self, k_fc):
        if self.done:
            raise InputError("tuning: the search is finished; read .result")
        if not np.isclose(k_fc, self._pending, rtol=0, atol=1e-12 * max(1.0, abs(k_fc))):
            raise InputError(f"tuning: told K_fc = {k_fc}, but the search asked {self._pending}")

    def _advance(self, told):
        """Send ``told`` to the generator; True when it finished (its result is kept)."""
        try:
            self._pending = self._gen.send(told)
        except StopIteration as stop:
            self._result = stop.value
            return True
        return False

    def run(self, measure):
        """Drive the search with a callable ``measure(k_fc)`` (tests, offline): the
        objective value, or for :class:`KfcSearch` the per-period HOSIDFs."""
        while not self.done:
            k = self.ask()
            self.tell(k, measure(k))
        return self.result


class _AskTell(_GeneratorSearch):
    """A scalar-objective search (``value = yield k``) with an evaluation budget."""

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
        self._start()

    def tell(self, k_fc, value):
        """Report the objective measured at ``k_fc`` (must be the value just asked)."""
        self._check_told(k_fc)
        value = float(value)
        if not np.isfinite(value):
            raise InputError(f"tuning: objective at K_fc = {k_fc} is not finite ({value})")
        self.history.append((float(self._pending), value))
        # let the algorithm see the value, then stop it if it did not finish within budget
        if not self._advance(value) and len(self.history) >= self.max_evaluations:
            self._result = self._finish(converged=False, reason="max_evaluations reached")

    @property
    def result(self):
        """:class:`TuningResult` once :attr:`done`, else the current best guess."""
        if self._result is not None:
            return self._result
        return self._finish(converged=False, reason="running")


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


# ---------------------------------------------------------------------------------------
# The measured-data search: a bracket it proves, a root search where the phases are stable,
# a ratio minimiser where they are not, and sigma(K_fc*) from the measured noise.
# ---------------------------------------------------------------------------------------
ODD_LEVEL_DEFINITION = ("rms of |H_k| over the odd harmonics k = 3, 5, .. K re |H_1| "
                        "(fftune.analysis.tuning.odd_ratio)")


def harmonic_orders(n_harmonics, parity="odd"):
    """The harmonic orders combined into a level: odd 3, 5, .. <= K, or even 2, 4, .. <= K.

    The one definition of the odd (even) harmonic level used by quantify and tune alike:
    ``odd_ratio(H, harmonic_orders(K))``, the rms of those |H_k| over |H_1|.
    """
    n_harmonics = int(n_harmonics)
    start = 3 if parity == "odd" else 2
    orders = tuple(range(start, n_harmonics + 1, 2))
    if not orders:
        raise InputError(f"tuning: no {parity} harmonic >= {start} among H_1 .. H_{n_harmonics}")
    return orders


@dataclass
class SearchPoint:
    """One closed-loop experiment of :class:`KfcSearch`.

    Attributes
    ----------
    k_fc : float
    H : ndarray of complex, shape (K,)
        HOSIDFs averaged over the recorded periods.
    H_periods : ndarray of complex, shape (P, K), or None
        HOSIDFs of each recorded period (their spread is the measured noise); None when
        the point was told as moments (:meth:`KfcSearch.tell_moments`).
    ratio, ratio_std : float
        :func:`odd_ratio` and its standard error from the period spread (inf when the
        motor did not follow the sine at all, |H_1| ~ 0).
    H_var : ndarray, shape (K,)
        Period-to-period variance of one period's complex H_k, E|H_p,k - H_k|^2.
    n_periods : int
        P, the recorded periods behind ``H``.
    """

    k_fc: float
    H: np.ndarray
    H_periods: object
    ratio: float
    ratio_std: float
    H_var: np.ndarray = None
    n_periods: int = 0


@dataclass
class KfcSearchResult:
    """Outcome of :class:`KfcSearch`.

    Attributes
    ----------
    k_fc : float
        K_fc* (feed-forward unit); the best measured point when not converged.
    sigma : float
        Standard uncertainty of K_fc*: the measured noise of the signed objective through
        its local slope (small-sample corrected so that +-2 sigma is a 95 % interval),
        combined with the distance to the verification experiment. NaN when not converged.
    converged : bool
    reason : str
        Why it stopped; when not converged, what to change.
    n_experiments : int
    bracket : (float, float)
        The last bracket proven to hold the ratio minimum (NaN, NaN if none).
    extended_to : float or None
        The upper end the bracket was extended to when ``upper`` was too small.
    regime : str
        ``"signed root"`` (stable odd phases) or ``"ratio minimiser"`` (the odd HOSIDF
        phases rotate with K_fc, e.g. stick-slip) or ``"none"``.
    sigma_signed : float
        Standard error of one signed-objective value (pooled over the experiments).
    slope : float
        ds/dK_fc at K_fc* (1/feed-forward unit).
    points : list of SearchPoint
    phases : ndarray or None
        The reference phases phi_i (rad) of the signed objective at K_fc* (signed root
        regime), for experiments made after the search (:func:`signed_point`).
    sigma_fit : float
        The flatness / model part: half the distance between the two root models of s near
        K_fc* (the over-compensated secant and the line across the sign change), 0 when
        only one applies (feed-forward unit).
    cause : str or None
        Not converged: ``"noise"`` when the noise of s is what kept the estimate from being
        verified, ``"not verified"`` when it was not the noise, ``"drive limit"``; None
        when converged.
    """

    k_fc: float
    sigma: float
    converged: bool
    reason: str
    n_experiments: int
    bracket: tuple
    extended_to: object
    regime: str
    sigma_signed: float
    slope: float
    points: list = field(default_factory=list)
    phases: object = None
    sigma_fit: float = 0.0
    cause: object = None


def _t_factor(dof):
    """t_{0.977, dof} / 2: scales a standard error estimated with ``dof`` degrees of
    freedom so that +-2 sigma is a 95 % interval (1 for many dof)."""
    # the inverse of Student's t CDF from scipy.special (= scipy.stats.t.ppf, without
    # importing scipy.stats: 0.9 s here, about 30 s in the emulated test guest)
    from scipy.special import stdtrit
    if dof < 1:
        return np.inf
    return float(stdtrit(dof, 0.9772)) / 2.0


class KfcSearch(_GeneratorSearch):
    """Ask/tell K_fc search on measured HOSIDFs, one closed-loop experiment per step.

    1. Bracket: the ends ``lower`` and ``upper`` are measured, then the root of the
       signed objective between them (reference phases from H(lower) - H(upper)). The
       bracket is proven when a measured point has a smaller ratio r than its measured
       neighbours on both sides. While the smallest r is at the top end, the top is
       doubled (up to ``k_limit``, what the drive allows); ``extended_to`` says so.
    2. Refine inside the proven bracket [a, b]: with reference phases from H(a) - H(b)
       the signed objective s is checked to fall monotonically (within the noise) over
       the points in [a, b]. Then a root search (secant / inverse quadratic,
       safeguarded to the sign change); else (the odd phases rotate with K_fc, as in
       stick-slip) a parabolic step on r^2, safeguarded to the bracket (golden section).
    3. Stop when the last experiment lies within the stopping tolerance of the estimate,
       its s is zero within 2 standard errors and its ratio is not above another
       measured point's by more than the noise: that experiment is the verification at
       K_fc*. The tolerance is max(sigma(K_fc*), ``rtol`` K_fc*, ``xtol``).

    Parameters
    ----------
    lower, upper : float
        Initial bracket (``lower`` >= 0, usually 0).
    k_limit : float
        Largest K_fc the bracket may be extended to (the drive's limit), >= ``upper``.
    harmonics : sequence of int
        Odd harmonics of the objective.
    max_experiments : int
    xtol : float
        Absolute floor of the stopping tolerance (feed-forward unit).
    rtol : float
        Relative floor of the stopping tolerance.

    Use ``ask()`` for the next K_fc, ``tell(k_fc, H_periods)`` with the (P, K) HOSIDFs of
    each recorded period (P >= 2), or ``tell_moments(k_fc, H, H_var, P)`` with their mean
    and period-to-period variance (a drive's line statistics), until ``done``; then
    ``result``.
    """

    def __init__(self, lower, upper, k_limit=None, harmonics=DEFAULT_HARMONICS, max_experiments=8,
                 xtol=0.0, rtol=5e-3):
        lower, upper = float(lower), float(upper)
        k_limit = upper if k_limit is None else float(k_limit)
        if not (np.isfinite(lower) and np.isfinite(upper) and 0 <= lower < upper):
            raise InputError(f"tuning: bracket must satisfy 0 <= lower < upper, got [{lower}, {upper}]")
        if not (np.isfinite(k_limit) and k_limit >= upper):
            raise InputError(f"tuning: k_limit must be >= upper = {upper}, got {k_limit}")
        if int(max_experiments) < 3:
            raise InputError("tuning: max_experiments must be >= 3")
        self.lower, self.upper, self.k_limit = lower, upper, k_limit
        self.harmonics = tuple(harmonics)
        self.max_experiments = int(max_experiments)
        self.xtol, self.rtol = float(xtol), float(rtol)
        self.points = {}
        self.extended_to = None
        self.regime = "none"
        self._ref = None          # the bracket whose ends give the reference phases
        self._noise_limited = 0.0  # sigma through the slope when it exceeded the tolerance last
        self._start()

    # ---- ask / tell ---------------------------------------------------------------------
    def tell(self, k_fc, H_periods):
        """Report the HOSIDFs of each recorded period measured at ``k_fc``."""
        self._check_told(k_fc)
        Hp = np.asarray(H_periods, dtype=complex)
        if Hp.ndim != 2 or Hp.shape[0] < 2:
            raise InputError(f"tuning: need the HOSIDFs of >= 2 recorded periods, shape (P, K); "
                             f"got {Hp.shape}")
        if not np.all(np.isfinite(Hp)):
            raise InputError(f"tuning: HOSIDFs at K_fc = {k_fc} are not finite")
        self.points[float(self._pending)] = self._point(float(self._pending), Hp)
        self._advance(None)

    def tell_moments(self, k_fc, H, H_var, n_periods):
        """Report the HOSIDFs measured at ``k_fc`` as their mean over the recorded periods
        and the period-to-period variance of one period's H_k (what a drive's line
        statistics give, :func:`fftune.analysis.stats.period_hosidf_moments`) instead of
        the HOSIDFs of each period.

        The standard errors of the ratio and of the signed objective then come from first-
        order error propagation with the lines taken as independent and circular (real and
        imaginary parts of equal variance, uncorrelated); with per-period HOSIDFs
        (:meth:`tell`) they are the spread of the per-period values.

        Parameters
        ----------
        k_fc : float
            The K_fc asked for.
        H : array_like of complex, shape (K,)
            Mean HOSIDFs H_1 .. H_K.
        H_var : array_like of float, shape (K,)
            E|H_p,k - H_k|^2 of one period p (>= 0).
        n_periods : int
            P >= 2.
        """
        self._check_told(k_fc)
        H = np.asarray(H, dtype=complex)
        H_var = np.asarray(H_var, dtype=float)
        P = int(n_periods)
        if H.ndim != 1 or H_var.shape != H.shape:
            raise InputError(f"tuning: need H and H_var of one shape (K,); got {H.shape} and {H_var.shape}")
        if P < 2:
            raise InputError(f"tuning: need the moments of >= 2 recorded periods, got {P}")
        if not (np.all(np.isfinite(H)) and np.all(np.isfinite(H_var)) and np.all(H_var >= 0)):
            raise InputError(f"tuning: HOSIDF moments at K_fc = {k_fc} are not finite (or a "
                             "negative variance)")
        k = float(self._pending)
        self.points[k] = self._point_from_moments(k, H, H_var, P)
        self._advance(None)

    @property
    def result(self):
        if self._result is not None:
            return self._result
        return self._fail("running")

    # ---- objective and its noise --------------------------------------------------------
    def _point(self, k, Hp):
        H = Hp.mean(axis=0)
        h1 = np.abs(H[0])
        moving = h1 > 1e-3 * np.max(np.abs(Hp[:, 0])) and h1 > 1e-6
        if moving:
            r = float(odd_ratio(H, self.harmonics))
            r_p = np.asarray(odd_ratio(Hp, self.harmonics))
            r_std = float(np.std(r_p, ddof=1) / np.sqrt(len(r_p)))
        else:
            r, r_std = np.inf, 0.0
        d = Hp - H
        H_var = np.sum(d.real ** 2 + d.imag ** 2, axis=0) / (len(Hp) - 1)
        return SearchPoint(k, H, Hp, r, r_std, H_var, len(Hp))

    def _point_from_moments(self, k, H, H_var, P):
        h1 = np.abs(H[0])
        moving = h1 > 1e-3 * (h1 + np.sqrt(H_var[0])) and h1 > 1e-6
        if moving:
            r = float(odd_ratio(H, self.harmonics))
            # r = q / |H_1|, q = sqrt(mean_i |H_i|^2): d r / d H_i = H_i / (n q |H_1|),
            # d r / d |H_1| = -r / |H_1|; a circular line of variance v adds v / 2 per
            # unit gradient
            n = len(self.harmonics)
            q = r * h1
            hi = np.array([_harmonic(H, i) for i in self.harmonics])
            vi = np.array([_harmonic(H_var, i) for i in self.harmonics])
            if q > 0:
                var_q = float(np.sum(np.abs(hi) ** 2 * vi)) / (2 * (n * q) ** 2)
            else:
                var_q = float(np.sum(vi)) / (2 * n ** 2)
            var_r = var_q / h1 ** 2 + r ** 2 * H_var[0] / (2 * h1 ** 2)
            r_std = float(np.sqrt(var_r / P))
        else:
            r, r_std = np.inf, 0.0
        return SearchPoint(k, H, None, r, r_std, H_var, P)

    def _signed(self, pts, phases):
        """s and its standard error at each point (inf-ratio points get NaN)."""
        out = [signed_point(p, phases, self.harmonics) if np.isfinite(p.ratio) else (np.nan, np.nan)
               for p in pts]
        return np.array([o[0] for o in out]), np.array([o[1] for o in out])

    def _phases(self, a, b):
        return reference_phases(self.points[a].H - self.points[b].H, self.harmonics)

    def _sorted(self):
        return [self.points[k] for k in sorted(self.points)]

    def _tol(self, k):
        return max(self.xtol, self.rtol * abs(k), 1e-12)

    def _fail(self, reason, bracket=(np.nan, np.nan)):
        pts = self._sorted()
        finite = [p for p in pts if np.isfinite(p.ratio)]
        best = min(finite, key=lambda p: p.ratio).k_fc if finite else np.nan
        return KfcSearchResult(k_fc=best, sigma=np.nan, converged=False, reason=reason,
                               n_experiments=len(pts), bracket=tuple(bracket),
                               extended_to=self.extended_to, regime=self.regime,
                               sigma_signed=np.nan, slope=np.nan, points=pts)

    # ---- the search ---------------------------------------------------------------------
    def _run(self):
        lo, hi = self.lower, self.upper
        yield hi
        yield lo
        # the first interior point: the root of s between the ends
        pa, pb = self.points[lo], self.points[hi]
        guess = None
        if np.isfinite(pa.ratio) and np.isfinite(pb.ratio):
            s, _ = self._signed([pa, pb], self._phases(lo, hi))
            if s[0] > 0 > s[1]:
                guess = lo + (hi - lo) * s[0] / (s[0] - s[1])
            elif s[0] > s[1] > 0 and pb.ratio < pa.ratio and hi < self.k_limit:
                # both ends under-compensated: extend at once, to the extrapolated zero of
                # s (with a margin), at least 1.25 and at most 4 times the upper end
                root = lo + (hi - lo) * s[0] / (s[0] - s[1])
                guess = min(self.k_limit, max(1.25 * hi, min(4 * hi, 1.15 * root)))
                self.extended_to = guess
        if guess is None or not (lo + 0.05 * (hi - lo) < guess < hi - 0.05 * (hi - lo)) \
                and self.extended_to is None:
            guess = lo + 0.5 * (hi - lo)
        yield guess
        while True:
            if len(self.points) >= self.max_experiments:
                return self._finish_or_fail("max_experiments reached")
            pts = self._sorted()
            ks = np.array([p.k_fc for p in pts])
            rs = np.array([p.ratio for p in pts])
            i = int(np.argmin(rs))
            if i == len(pts) - 1:
                # smallest ratio at the top: the optimum may lie above it
                top = ks[-1]
                if top >= self.k_limit * (1 - 1e-9):
                    res = self._fail(
                        f"the odd-harmonic ratio is smallest at the drive's limit K_fc = {top:.4g} "
                        "(bracket cannot be extended): check the friction level, lower the drive's "
                        "u_max limit only if it is below the friction, or raise the sine amplitude",
                        (ks[-2], top))
                    res.cause = "drive limit"
                    return res
                new = min(2 * top, self.k_limit)
                self.extended_to = new
                yield new
                continue
            # bracket [a, b] around the smallest ratio (a = the lower end when it is smallest)
            a = ks[i - 1] if i > 0 else ks[0]
            b = ks[i + 1]
            est = self._estimate(a, b)
            if est["stop"]:
                return est["result"]
            nxt = est["next"]
            known = np.array(sorted(self.points))
            if np.min(np.abs(known - nxt)) <= 1e-9 * max(1.0, abs(nxt)):
                # the step repeats an experiment: it cannot add information
                return self._finish_or_fail(f"the search stalled at K_fc = {nxt:.6g} (no new "
                                            "experiment to make)")
            yield nxt

    def _estimate(self, a, b):
        """Next experiment in the proven bracket [a, b], or the final result."""
        # Where s is trusted: the earlier bracket whose ends gave the reference phases, if
        # it holds this one and s falls monotonically over it (near the optimum the ratio
        # sits on its floor and its minimum wanders, the sign change of s does not); else
        # this bracket with phases from its own ends (a sub-bracket where the phases are
        # stable); else none: the odd phases rotate with K_fc.
        candidates = []
        if self._ref is not None and self._ref[0] <= a and b <= self._ref[1]:
            candidates.append(self._ref)
        if np.isfinite(self.points[a].ratio) and (a, b) not in candidates:
            candidates.append((a, b))
        monotone = False
        for ref in candidates:
            pts = [p for p in self._sorted() if ref[0] <= p.k_fc <= ref[1]]
            phases = self._phases(*ref)
            s, s_se = self._signed(pts, phases)
            noise = 2 * np.sqrt(s_se[:-1] ** 2 + s_se[1:] ** 2)
            if bool(np.all(np.diff(s) < noise)) and s[0] > 0 > s[-1]:
                monotone = True
                self._ref = ref
                a, b = ref
                break
        if not monotone:
            pts = [p for p in self._sorted() if a <= p.k_fc <= b]
            phases = self._phases(a, b) if np.isfinite(self.points[a].ratio) else None
        ks = np.array([p.k_fc for p in pts])
        rs = np.array([p.ratio for p in pts])
        pooled = self._pooled_signed_se(phases) if phases is not None else np.nan
        if monotone:
            self.regime = "signed root"
            j = int(np.nonzero((s[:-1] > 0) & (s[1:] <= 0))[0][0])
            k1, k2, s1, s2 = ks[j], ks[j + 1], s[j], s[j + 1]
            root = k1 + (k2 - k1) * s1 / (s1 - s2)
            root_linear = root
            # Over-compensated (s < 0) the loop does not stick and s is close to linear in
            # K_fc; under-compensated it bends (stick-slip). So: the secant through the two
            # over-compensated points nearest the root when there are two, else the
            # linear interpolation across the sign change; kept only inside the sign change.
            over = np.nonzero(s < 0)[0]
            if len(over) >= 2:
                o1, o2 = over[0], over[1]
                sec = ks[o1] - s[o1] * (ks[o2] - ks[o1]) / (s[o2] - s[o1])
                if k1 < sec < k2:
                    root = sec
            slope = (s2 - s1) / (k2 - k1)
            dof = self._dof()
            near = np.abs(ks - root) <= 0.25 * abs(root)
            if np.count_nonzero(near) >= 4:
                # lack of fit of a line through the points near the root: the K-to-K
                # scatter (quantisation, limit cycles) that the period spread does not see
                fit = np.polyfit(ks[near], s[near], 1)
                slope = fit[0] if fit[0] < 0 else slope
                lof = float(np.sqrt(np.sum((s[near] - np.polyval(fit, ks[near])) ** 2)
                                    / (np.count_nonzero(near) - 2)))
                if lof > pooled:
                    pooled, dof = lof, np.count_nonzero(near) - 2
            sigma_noise = pooled / abs(slope) * _t_factor(dof) if slope != 0 else np.inf
            tol = max(sigma_noise, self._tol(root))
            self._noise_limited = float(sigma_noise) if sigma_noise > self._tol(root) else 0.0
            # the verification: a measured point at the estimate, s = 0 within the noise,
            # ratio not above another point's by more than the noise
            m = int(np.argmin(np.abs(ks - root)))
            pm = pts[m]
            # points closer than 2 tol to the estimate are the same K_fc within the
            # resolution; every other measured ratio must not be below the verification's
            # by more than the noise
            others = [p for p in self._sorted() if abs(p.k_fc - root) > 2 * tol] or [pm]
            best = min(others, key=lambda p: p.ratio)
            r_ok = pm.ratio <= best.ratio + 2 * np.hypot(pm.ratio_std, best.ratio_std) + 0.01 * best.ratio
            # and a local minimum: the nearest measured point on each side (beyond the
            # resolution) has a larger ratio, within the noise only
            for side in ([p for p in others if p.k_fc < root][-1:], [p for p in others if p.k_fc > root][:1]):
                for q in side:
                    r_ok = r_ok and q.ratio >= pm.ratio - 2 * np.hypot(pm.ratio_std, q.ratio_std)
            s_ok = abs(s[m]) <= 2 * max(s_se[m], pooled) + abs(slope) * self._tol(root)
            narrow = (k2 - k1) <= 4 * tol
            if abs(ks[m] - root) <= tol and r_ok and (s_ok or narrow):
                # s_ok: s(K_m) = 0 within the noise; narrow: the sign change is bracketed
                # within the tolerance, s's K-to-K scatter (quantisation) exceeds the noise
                sigma = np.hypot(sigma_noise, abs(ks[m] - root))
                if not s_ok:
                    sigma = np.hypot(sigma, (k2 - k1) / np.sqrt(12))
                what = (f"s = {s[m]:.3g} (noise {max(s_se[m], pooled):.2g})" if s_ok else
                        f"the sign change of s bracketed in [{k1:.6g}, {k2:.6g}]")
                return {"stop": True, "result": KfcSearchResult(
                    k_fc=float(root), sigma=float(sigma), converged=True,
                    reason=(f"verified: the experiment at K_fc = {ks[m]:.6g} has {what} and the "
                            "smallest ratio within the noise"),
                    n_experiments=len(self.points), bracket=(float(a), float(b)),
                    extended_to=self.extended_to, regime=self.regime,
                    sigma_signed=float(pooled), slope=float(slope), points=self._sorted(),
                    phases=np.array(phases, dtype=float), sigma_fit=float(abs(root - root_linear) / 2))}
            nxt = root
            if min(abs(ks - nxt)) < 0.25 * tol:
                # the estimate sits on a measured point that did not verify: probe the noise
                # width beside it, on the side of the sign change
                nxt = root + (tol if s[m] > 0 else -tol)
                if not k1 < nxt < k2:
                    nxt = 0.5 * (k1 + k2)
            return {"stop": False, "next": float(np.clip(nxt, a + 1e-12, b - 1e-12))}
        # phases rotate with K_fc (or the lower end does not move): safeguarded ratio minimiser
        self.regime = "ratio minimiser"
        i = int(np.argmin(rs))
        x = ks[i]
        lo_k = ks[i - 1] if i > 0 else a
        hi_k = ks[i + 1] if i + 1 < len(ks) else b
        width = hi_k - lo_k
        if width <= 2 * self._tol(x):
            sig = width / 2 / np.sqrt(3)
            return {"stop": True, "result": KfcSearchResult(
                k_fc=float(x), sigma=float(max(sig, self._tol(x))), converged=True,
                reason=(f"ratio minimiser: bracket [{lo_k:.6g}, {hi_k:.6g}] below the tolerance; the "
                        "odd HOSIDF phases rotate with K_fc, so the signed root search was not used"),
                n_experiments=len(self.points), bracket=(float(lo_k), float(hi_k)),
                extended_to=self.extended_to, regime=self.regime,
                sigma_signed=float(pooled), slope=np.nan, points=self._sorted())}
        u = None
        if i > 0 and i + 1 < len(ks) and np.isfinite(rs[i - 1]):
            f0, f1, f2 = rs[i - 1] ** 2, rs[i] ** 2, rs[i + 1] ** 2
            x0, x1, x2 = lo_k, x, hi_k
            den = (x1 - x0) * (f1 - f2) - (x1 - x2) * (f1 - f0)
            if den != 0:
                u = x1 - 0.5 * ((x1 - x0) ** 2 * (f1 - f2) - (x1 - x2) ** 2 * (f1 - f0)) / den
        gold = 0.381966
        small = 0.1 * width
        if u is None or not (lo_k + small < u < hi_k - small) or abs(u - x) < max(small / 2, self._tol(x)):
            u = x + gold * (hi_k - x) if (hi_k - x) > (x - lo_k) else x - gold * (x - lo_k)
        return {"stop": False, "next": float(u)}

    def _pooled_signed_se(self, phases):
        pts = [p for p in self._sorted() if np.isfinite(p.ratio)]
        _, se = self._signed(pts, phases)
        return pooled_standard_error(se)

    def _dof(self):
        return sum(p.n_periods - 1 for p in self.points.values() if np.isfinite(p.ratio))

    def _finish_or_fail(self, reason):
        if self._noise_limited:
            res = self._fail(f"{reason} before the estimate was verified: the noise of s through its "
                             f"slope ({self._noise_limited:.3g}) is wider than the stopping tolerance; raise "
                             f"the periods per experiment or tune.search.max_experiments (now "
                             f"{self.max_experiments})")
            res.cause = "noise"
            return res
        res = self._fail(f"{reason} before the estimate was verified, and not because of the noise (s "
                         "moves between the experiments by more than its measured noise: a plant that "
                         "changed, a loop that does not follow the sine, a smoothed sign; or odd "
                         "phases that rotate with K_fc): raise tune.search.max_experiments (now "
                         f"{self.max_experiments}) only when none of these applies")
        res.cause = "not verified"
        return res


# ---------------------------------------------------------------------------------------
# After the search: experiments at other conditions, the checks of every experiment, the
# uncertainty budget (sigma_total) and the amplitude decision.
# ---------------------------------------------------------------------------------------
def signed_point(point, phases, harmonics=DEFAULT_HARMONICS):
    """The signed objective s of one :class:`SearchPoint` and its standard error.

    With per-period HOSIDFs the standard error is the spread of the per-period s over
    sqrt(P); with moments (line statistics) first-order propagation: gradient
    1 / (n |H_1|) per line (a circular line of variance v adds v / 2), -s / |H_1| through
    |H_1|.

    Returns
    -------
    (s, se) : (float, float)
        NaN, NaN when the motor did not follow (|H_1| ~ 0).
    """
    h1 = float(np.abs(point.H[0]))
    if not (h1 > 1e-6 and np.isfinite(point.ratio)):
        return np.nan, np.nan
    s_k = float(signed_odd_ratio(point.H, phases, harmonics))
    if point.H_periods is not None:
        sp = np.asarray(signed_odd_ratio(point.H_periods, phases, harmonics))
        return s_k, float(np.std(sp, ddof=1) / np.sqrt(len(sp)))
    n = len(harmonics)
    vi = np.array([_harmonic(point.H_var, i) for i in harmonics])
    var_s = float(np.sum(vi)) / (2 * (n * h1) ** 2) + s_k ** 2 * point.H_var[0] / (2 * h1 ** 2)
    return s_k, float(np.sqrt(var_s / point.n_periods))


def make_point(k_fc, H_periods=None, H=None, H_var=None, n_periods=None,
               harmonics=DEFAULT_HARMONICS):
    """A :class:`SearchPoint` from per-period HOSIDFs (P, K) or from moments (H, H_var, P),
    as :meth:`KfcSearch.tell` / :meth:`KfcSearch.tell_moments` build them."""
    helper = KfcSearch.__new__(KfcSearch)
    helper.harmonics = tuple(harmonics)
    if H_periods is not None:
        return helper._point(float(k_fc), np.asarray(H_periods, dtype=complex))
    return helper._point_from_moments(float(k_fc), np.asarray(H, dtype=complex),
                                      np.asarray(H_var, dtype=float), int(n_periods))


def pooled_standard_error(standard_errors):
    """The pooled standard error of one value from experiments of (possibly) unequal noise:
    the root mean square of their standard errors (the mean would understate it: an
    experiment twice as noisy counts four times in the variance). NaN when none is finite."""
    se = np.asarray(standard_errors, dtype=float)
    se = se[np.isfinite(se)]
    return float(np.sqrt(np.mean(se ** 2))) if len(se) else np.nan


# Saturation and motion of one tune experiment.
SATURATION_MAX_FRACTION = 0.02   # more samples at u_max: the loop is not the linear loop tuned
MOTION_MIN_H1 = 0.2              # |H_1| below this: the motor does not follow the sine


def check_experiment(h1_abs, saturated_fraction=None, u_rms_re_max=None, amplitude_rad=None,
                     u_max_v=None):
    """Saturation and motion of one closed-loop sine experiment.

    Parameters
    ----------
    h1_abs : float
        |H_1| reference -> motor angle (the motion re the commanded sine; 1 = follows).
    saturated_fraction : float or None
        Fraction of the recorded samples with |u| at u_max (raw samples).
    u_rms_re_max : float or None
        rms(u) / u_max (line statistics, no samples): a lower bound of the samples within
        20 % of u_max is (rho^2 - 0.64) / 0.36.
    amplitude_rad, u_max_v : float or None
        For the message.

    Returns
    -------
    dict
        ``saturated_fraction`` (measured or the lower bound), ``saturation_basis``,
        ``motion_h1``, ``cause`` (None, ``"saturation"`` or ``"no motion"``) and ``text``.
    """
    h1 = float(h1_abs) if h1_abs is not None and np.isfinite(h1_abs) else 0.0
    basis, frac = None, None
    if saturated_fraction is not None:
        basis, frac = "samples at u_max", float(saturated_fraction)
    elif u_rms_re_max is not None and np.isfinite(u_rms_re_max):
        rho2 = float(u_rms_re_max) ** 2
        basis, frac = "lower bound from rms(u) / u_max (samples within 20 % of u_max)", \
            max(0.0, (rho2 - 0.64) / 0.36)
    umax = f" = {u_max_v:g} V" if u_max_v else ""
    at = f" at {amplitude_rad:g} rad" if amplitude_rad else ""
    cause, text = None, ""
    if h1 < MOTION_MIN_H1:
        cause = "no motion"
        text = (f"the motor does not follow the sine{at} (|H_1| = {h1:.3g} < {MOTION_MIN_H1:g})")
        if frac is not None and frac > SATURATION_MAX_FRACTION:
            text += (f" while the drive output sits at its limit u_max{umax} "
                     f"({100 * frac:.0f} % of the samples, {basis}): the friction exceeds what the "
                     "drive can give; raise u_max (it must exceed the break-away friction) or reduce "
                     "the friction")
        else:
            text += ": the break-away friction holds it; raise the amplitude or check the set-up"
    elif frac is not None and frac > SATURATION_MAX_FRACTION:
        cause = "saturation"
        text = (f"the drive output is at its limit u_max{umax} in {100 * frac:.0f} % of the samples"
                f"{at} ({basis}; at most {100 * SATURATION_MAX_FRACTION:g} %): the friction plus "
                "the sine's demand exceed u_max, the loop is not the one being tuned; lower the "
                "amplitude or the frequency, or raise u_max")
    return {"saturated_fraction": frac, "saturation_basis": basis, "motion_h1": h1,
            "cause": cause, "text": text}


def viscous_feedforward_estimate(U1, Y1, omega_rad_s, k_fc):
    """The velocity feed-forward K_v (V s/rad) that cancels the viscous friction seen at the
    plant input, from one experiment's fundamentals.

    With the plant input u (V, the feed-forward included) and the motor angle y at the
    sine's fundamental, a plant J y'' + b y' + F_c sgn(y') = k_m u gives
    Im(U1 / Y1) / omega = b / k_m + 4 F_c / (pi k_m |Y1| omega) (the friction's describing
    function, in phase with the velocity); with F_c / k_m ~ K_fc (the estimate):
    K_v = Im(U1 / Y1) / omega - 4 K_fc / (pi |Y1| omega). Any lag of the motor behind the
    reference (viscous friction, load-side damping through a stiff shaft) moves the
    reversal of the motor's velocity away from the reversal of sgn(reference velocity) that
    switches the Coulomb feed-forward; the odd-ratio criterion's optimum then moves off the
    Coulomb level (by several % at a 5 deg lag, tens of % at 20 deg). K_v removes the lag.

    Parameters
    ----------
    U1, Y1 : complex
        Amplitude phasors of the fundamental: plant input (V) and motor angle (rad).
    omega_rad_s : float
    k_fc : float
        The Coulomb level per volt taken for the friction's describing function.

    Returns
    -------
    float
        K_v >= 0 (0 when the estimate is negative or not finite).
    """
    U1, Y1 = complex(U1), complex(Y1)
    if not (abs(Y1) > 0 and omega_rad_s > 0):
        return 0.0
    kv = (U1 / Y1).imag / omega_rad_s - 4 * float(k_fc) / (np.pi * abs(Y1) * omega_rad_s)
    return float(kv) if np.isfinite(kv) and kv > 0 else 0.0


def root_at_slope(k_fc, s, slope):
    """K_fc where s reaches 0 along the slope ds/dK (< 0) from one experiment (k_fc, s)."""
    if not (np.isfinite(s) and np.isfinite(slope) and slope < 0):
        return np.nan
    return float(k_fc - s / slope)


def encoder_floor_v(encoder_step_rad, amplitude_rad, noise_rad, slope):
    """The encoder-quantisation part of sigma(K_fc*) (feed-forward unit).

    A sine of amplitude A measured with a step q carries quantisation harmonics of
    relative size about (q / A)^(3/2) / pi at the low odd orders (the staircase's error
    spreads over about A / q orders); measurement noise of standard deviation sigma_n
    dithers it by exp(-2 pi^2 sigma_n^2 / q^2) (the first Fourier term of the
    quantiser's error). Their phase does not follow K_fc: an offset of s of that size,
    through the slope, is the floor. 0 without an encoder step (ideal sensor).
    """
    q = float(encoder_step_rad or 0.0)
    if not (q > 0 and amplitude_rad > 0 and np.isfinite(slope) and slope != 0):
        return 0.0
    ds = (q / amplitude_rad) ** 1.5 / np.pi * np.exp(-2 * np.pi ** 2 * (noise_rad / q) ** 2)
    return float(ds / abs(slope))


def uncertainty_budget(parts):
    """sigma_total = the root sum of squares of the parts (independent contributions).

    Parameters
    ----------
    parts : dict
        name -> standard uncertainty (feed-forward unit); None / NaN parts are skipped.

    Returns
    -------
    (total, parts) : (float, dict)
        The total and the parts kept (floats).
    """
    kept = {k: float(v) for k, v in parts.items() if v is not None and np.isfinite(v)}
    return float(np.sqrt(sum(v ** 2 for v in kept.values()))), kept


def encoder_step_estimate(y, noise_rad=0.0):
    """The quantisation step of a recorded angle with additive measurement noise, or None.

    The sample-to-sample changes of a slowly moving quantised angle are 0 or +-q (plus the
    noise, standard deviation sqrt(2) sigma_n): q is the median of the smallest cluster of
    changes above 4 sqrt(2) sigma_n, accepted when that cluster is tight (its spread at
    most a quarter of q) and holds >= 20 changes. None when noise hides the steps
    (sigma_n > q / 6: the quantiser is then dithered) or the signal is not quantised.
    """
    y = np.asarray(y, dtype=float).ravel()
    d = np.abs(np.diff(y[np.isfinite(y)]))
    floor = 4 * np.sqrt(2) * float(noise_rad) + 1e-12
    d = d[d > floor]
    if d.size < 20:
        return None
    c = float(np.percentile(d, 10))
    cluster = d[(d > 0.5 * c) & (d < 1.5 * c)]
    if cluster.size < 20:
        return None
    q = float(np.median(cluster))
    if np.std(cluster) > 0.25 * q or q < 6 * float(noise_rad):
        return None
    return q



def amplitude_combination(k1, sigma1, a1, k2, sigma2, a2, rule="trend"):
    """K_fc* from its values at two sine amplitudes, and the amplitude part of the budget.

    Parameters
    ----------
    k1, sigma1, a1 : float
        K_fc* at the first amplitude a1 (rad), its noise part.
    k2, sigma2, a2 : float
        The same at the second amplitude.
    rule : str
        ``"trend"`` (default): when the two differ by more than twice their combined noise
        (a real amplitude dependence), extrapolate linearly in 1/A to 1/A -> 0 (the
        offsets of stick-slip, asymmetry, quantisation and noise dither fall about as 1/A)
        and take the size of that step as the amplitude part; else the inverse-variance
        mean, their difference the part (the mean leans on the quieter one, which need not
        be the less biased). ``"extrapolate"``: always extrapolate.
        ``"first"``: k1, the whole difference the part.

    Returns
    -------
    (k, sigma_noise, amplitude_part, how) : (float, float, float, str)
    """
    d = k2 - k1
    noise_d = float(np.hypot(sigma1, sigma2))
    g = (1 / a1) / (1 / a1 - 1 / a2)          # k(1/A -> 0) = k1 + g (k2 - k1)
    if rule == "first":
        return float(k1), float(sigma1), float(abs(d)), "the first amplitude's K_fc*"
    if rule == "extrapolate" or abs(d) > 2 * noise_d:
        k = k1 + g * d
        noise = float(np.hypot((1 - g) * sigma1, g * sigma2))
        near = k1 if a1 > a2 else k2
        return float(k), noise, float(abs(k - near)), (
            f"K_fc* changes with the amplitude ({k1:.5g} at {a1:.3g} rad, {k2:.5g} at {a2:.3g} rad, "
            f"beyond twice the noise {noise_d:.2g}): extrapolated to 1/A -> 0, the step is the "
            "amplitude part")
    floor = 1e-9 * max(abs(k1), abs(k2), 1e-12)     # noise-free values: equal weights
    w1, w2 = 1 / max(sigma1, floor) ** 2, 1 / max(sigma2, floor) ** 2
    k = (w1 * k1 + w2 * k2) / (w1 + w2)
    return float(k), float(1 / np.sqrt(w1 + w2)), float(abs(d)), (
        f"K_fc* at {a1:.3g} and {a2:.3g} rad agree within twice their noise {noise_d:.2g}: their "
        "inverse-variance mean, the difference the amplitude part")


def viscous_from_harmonics(U, Y, omega_rad_s, n_period, cycles, orders=(1, 3)):
    """The viscous friction per volt, K_v (V s/rad), and the Coulomb level (V) of a rigid
    plant fitted to one experiment's plant-input and angle harmonics.

    k_m u = J y'' + b y' + F_c sgn(y') at the odd harmonics k (default 1 and 3):
    U_k = -J' (k w)^2 Y_k + b' j k w Y_k + F_c' S_k, with S_k the DFT lines of the sign of
    the velocity's fundamental (the relay the friction is while the motor slides) and the
    primes "per volt". Least squares over the real and imaginary parts; the relay's 1/k
    pattern at k = 3 separates F_c' from b'. The measured u contains the feed-forward, so
    any K_fc, K_v of the experiment may be used.

    Parameters
    ----------
    U, Y : array_like of complex, shape (K,)
        Unnormalised DFT lines (numpy.fft.fft of one period) at k * cycles, k = 1 .. K, of
        the plant input (V) and of the motor angle (rad).
    omega_rad_s : float
        The sine's angular frequency.
    n_period, cycles : int
        Samples per period and sine cycles in it.

    Returns
    -------
    (k_v, f_c) : (float, float)
        NaN, NaN when the lines do not determine them.
    """
    U, Y = np.asarray(U, dtype=complex), np.asarray(Y, dtype=complex)
    n, c = int(n_period), int(cycles)
    if not (len(U) >= max(orders) and len(Y) >= max(orders) and abs(Y[0]) > 0 and omega_rad_s > 0):
        return np.nan, np.nan
    t = np.arange(n)
    v1 = np.real(1j * Y[0] * np.exp(2j * np.pi * c * t / n))      # the velocity's fundamental
    S = np.fft.fft(np.sign(v1))
    rows, rhs = [], []
    for k in orders:
        w = k * omega_rad_s
        a = np.array([-(w ** 2) * Y[k - 1], 1j * w * Y[k - 1], S[k * c]])
        rows += [a.real, a.imag]
        rhs += [U[k - 1].real, U[k - 1].imag]
    x, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    if not np.all(np.isfinite(x)):
        return np.nan, np.nan
    return float(x[1]), float(x[2])


# ---------------------------------------------------------------------------------------
# Offsets of the criterion that no feed-forward removes: the loop's own lag, a smoothed
# sign, a plant that changes during the tune (issue 32).
# ---------------------------------------------------------------------------------------
# The named causes of an unconverged tune (results.yaml tune.search.cause).
STOP_CAUSES = ("saturation", "no motion", "unsettled", "noise", "loop lag", "smoothed sign",
               "non-stationary", "drive limit", "stick-slip", "amplitude dependence", "encoder",
               "flatness", "viscous", "budget", "not verified")
# the cause of a budget above its limit, by its largest part
PART_CAUSES = {"noise": "noise", "amplitude": "amplitude dependence", "encoder": "encoder",
               "flatness": "flatness", "viscous": "viscous", "loop_lag": "loop lag",
               "smoothed_sign": "smoothed sign"}

# The loop's lag at the tuning frequency: the motor lags the reference because of the PD
# loop's bandwidth, which K_v cannot remove. The feed-forward switches with the reference's
# velocity, the friction with the motor's, so the criterion's optimum moves off the Coulomb
# level, about quadratically in the lag (a relay shifted by phi projects on the reference's
# phase with cos(k phi) = 1 - (k phi)^2 / 2): on configs/plant_twomass.yaml with kp lowered
# (tests/bench/bench_tune_matrix.py, "slow loop") +0.4 % at 1.4 deg, +1.9 % at 3.9 deg,
# +3.8 % at 5.5 deg, +5.9 % at 6.5 deg, then erratic (-11 % at 14 deg; +25 % at 9 deg in
# issue 32). The part is LOOP_LAG_PART_PER_DEG2 lag^2 K_fc* (twice the largest bias seen per
# deg^2 below the limit, halved: 2 sigma covers it); above LOOP_LAG_MAX_DEG no result.
LOOP_LAG_PART_PER_DEG2 = 1.2e-3
LOOP_LAG_MAX_DEG = 7.0


def loop_lag_part(lag_deg, k_fc):
    """The loop-lag part of sigma(K_fc*) (feed-forward unit) for a residual lag of the motor
    behind the reference (deg; a lead counts the same): LOOP_LAG_PART_PER_DEG2 lag^2 |K_fc|.
    inf above LOOP_LAG_MAX_DEG (the offset is no longer bounded by the quadratic law)."""
    lag = abs(float(lag_deg))
    if not np.isfinite(lag):
        return np.inf
    if lag > LOOP_LAG_MAX_DEG:
        return np.inf
    return float(LOOP_LAG_PART_PER_DEG2 * lag ** 2 * abs(float(k_fc)))


def smoothed_sign_bias(width_rad_s, velocity_peak_rad_s, harmonics=DEFAULT_HARMONICS, n=4096):
    """Bound of the relative offset of K_fc* when the drive's feed-forward uses a smoothed
    sign, sat(v_ref / w), instead of sgn(v_ref), with the sine's reference velocity of peak
    V (rad/s): |1 / g - 1|, where each odd harmonic k of the feed-forward is c_k times the
    relay's (c_k from the DFT of sat(cos / rho), rho = w / V) and
    g = sum_k |c_k| / k / sum_k sgn(c_k) / k (the projection of the friction's relay on the
    feed-forward's phases, harmonics weighted as the relay's 1/k).

    The closed loop weights the harmonics differently (the plant falls with k): on
    configs/plant_twomass.yaml the offsets seen were smaller (rho 0.1: +0.2 % for a bound of
    3.8 %; rho 0.51: +8 % for 45 %), so it is a bound, carried as a part, not a correction.

    Returns
    -------
    float
        >= 0; 0 for w = 0 (pure sign); inf when the smoothing leaves no odd harmonic.
    """
    w, v = float(width_rad_s), float(velocity_peak_rad_s)
    if not w > 0:
        return 0.0
    if not v > 0:
        return np.inf
    th = 2 * np.pi * np.arange(n) / n
    ff = np.fft.fft(np.clip(np.cos(th) * (v / w), -1.0, 1.0))
    rl = np.fft.fft(np.sign(np.cos(th)))
    c = np.array([(ff[k] / rl[k]).real for k in harmonics])
    wk = 1.0 / np.asarray(harmonics, dtype=float)
    num, den = float(np.sum(wk * np.abs(c))), float(np.sum(wk * np.sign(c)))
    if not (den > 0 and num > 0):
        return np.inf
    return float(abs(den / num - 1.0))


def drift_between(k_first, k_repeat, sigma_first, sigma_repeat, floor=0.0):
    """Whether the same experiment repeated later in a tune read a different K_fc*: the
    plant changed in between (friction drift), rather than the amplitude or the noise.

    Parameters
    ----------
    k_first, k_repeat : float
        K_fc* read at the same amplitude (and K_v) at the two times.
    sigma_first, sigma_repeat : float
        Their noise parts.
    floor : float
        A difference below it is not counted (the repeatability of the loop: its
        resolution, e.g. the search's tolerance).

    Returns
    -------
    (changed, difference) : (bool, float)
        ``changed`` when |difference| > max(3 sqrt(sigma_first^2 + sigma_repeat^2), floor).
    """
    d = float(k_repeat) - float(k_first)
    if not np.isfinite(d):
        return False, d
    return bool(abs(d) > max(3 * float(np.hypot(sigma_first, sigma_repeat)), float(floor))), d


def halved_frequency(n_period, cycles, n_max=8192):
    """The tuning sine at half the frequency on the DFT grid: (N, cycles / 2) when the cycles
    per period are even, else (2 N, cycles) when 2 N <= ``n_max``; None when neither."""
    n, c = int(n_period), int(cycles)
    if c >= 2 and c % 2 == 0:
        return n, c // 2
    if 2 * n <= int(n_max):
        return 2 * n, c
    return None
