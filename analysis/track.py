"""Tracking friction from the machine's own repeated task (issue 26, docs/track.md).

The drive plays its task (point-to-point moves with a third-order profile and dwell) and
sums, per block of a repetition, the products of the reference-derived regressors

    phi = [p, n, v_r, a_r],  p = max(s, 0), n = min(s, 0), s = sgn(v_r) as the feed-forward uses it

with themselves (the *design* part) and with the plant input u (the *data* part), plus
sum e^2 and sum u^2 (firmware_sim/core/task.h, objects 0x2061 / 0x2062). The model is

    u = F_+ p + F_- n + b v_r + m a_r + (feedback of noise, model error)

(F_+ and F_- the Coulomb levels of the two directions as input voltage, b the viscous
coefficient, m = J / k_m the inertia). The regressors depend on the reference only: they are
the instruments of an instrumental-variable estimator (here Z = Phi), so measurement noise,
which enters u through the feedback and is uncorrelated with the reference, does not bias
the estimate. The closed loop does bias it while the feed-forward is wrong (the feedback
supplies the missing torque late, through the loop's bandwidth); the bias vanishes as the
feed-forward (K_fc, K_v and the task's mass feed-forward K_a) approaches the plant, so the
estimate is iterated task by task (iterative feed-forward tuning) and its fixed point is the
plant's friction. K_fc = (F_+ + F_-) / 2; (F_+ - F_-) / 2 is a constant load torque (or the
friction's asymmetry), which a task that never reverses cannot tell from Coulomb friction.

Uncertainty: the estimator's asymptotic (sandwich) covariance A^-1 (sum_b s2_b A_b) A^-1
with the residual variance s2_b of each block estimated from its sums (the noise), combined
with a systematic floor SYS_FLOOR_REL |K_fc| measured on the bench (the closed loop's fixed
point and the stick-slip loop's periodic states). Not a jackknife over the blocks: the blocks
hold different phases of the motion (the Coulomb information sits in the moves, a dwell
block holds none), so deleting one moves the estimate by the model error that differs
between phases, a deterministic part that does not vary from task to task: that sigma was
~30x the actual scatter. The model's own miss (the momentum at the moves' ends that the one
inertia term does not model) is a further part, from the gap between this estimate and one
with velocity instruments from the same sums (:func:`velocity_iv_k_fc`,
:func:`model_error_sigma`).

Pure numpy; no CAN code. The tracking policy (bounded updates, rollback, named stops) is
:class:`Tracker`.
"""
import math
import struct
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.errors import FftuneError

TASK_HEADER_BYTES = 8
DESIGN_NAMES = ("pp", "nn", "pv", "pa", "nv", "na", "vv", "va", "aa")
DATA_NAMES = ("pu", "nu", "vu", "au", "ee", "uu")
PARAM_NAMES = ("fc_pos", "fc_neg", "kv", "ka")
# identifiability limits (documented in docs/track.md)
COND_LIMIT = 1.0e6          # condition number of the correlation-normalised design matrix
KV_UNIQUE_MIN = 0.02        # fraction of v_r's energy not explained by p, n, a_r needed for K_v
# systematic floor of K_fc's sigma, relative to K_fc: the closed loop's fixed point and the
# periodic state the quantised stick-slip loop settles in move the settled estimate by
# -0.73 .. +0.43 % of the truth on plant_twomass (make bench, bench_track.py: the pause
# between runs, noise; docs/track.md); a noise-only sigma (~0.1 %) would not cover that
SYS_FLOOR_REL = 0.004
SCATTER_MIN = 5             # estimates (this one included) before their scatter is the sigma
SCATTER_WINDOW = 10         # newest estimates the scatter uses
# K_v held: a change of the viscous friction cannot be told from one of K_fc by a task whose
# velocity is nearly +-constant; it is folded into K_fc (docs/track.md)
NOTE_VISCOUS_FOLDED = "viscous_drift_folded_into_k_fc"
# K_v estimated as well: the closed loop moves torque between K_fc and K_v (the two are
# weakly separated by a point-to-point task), K_fc settles +1.6 % (plant_twomass) .. +3.6 %
# (20x its viscous friction) above the truth (make bench); the floor then is this fraction
SYS_FLOOR_KV_REL = 0.02
NOTE_KV_SPLIT = "k_fc_k_v_split_bias"
# K_v estimated as well, the split's conditioning: the four-gain fit equals the K_v-held fit
# with b at the fit's own K_v, so the two K_fc differ by what the proposed K_v change moves
# K_fc by (the held fit's K_fc per V s/rad times the change). Where the regressors p, n and
# v_r are nearly collinear over the task (a low Coulomb level, issue 32's fourth pass) a
# small model error in the data moves that K_v far and K_fc with it (-68 % at 0.5 x
# plant_twomass's Coulomb level, sigma 4.9 %). The gap against the held fit at the K_v in
# effect is a part of K_fc's sigma (``k_fc_sigma_split``); where it exceeds KV_SPLIT_MAX_REL
# of K_fc (the tracker's default limit on K_fc's sigma, TrackSettings.max_sigma_rel: a K_v
# change the tracker could not accept K_fc's uncertainty for) the task cannot tell the split:
# the estimate falls back to the K_v-held fit (K_v not identified, held at the value in
# effect) and the row says so (NOTE_KV_SPLIT_HELD)
KV_SPLIT_MAX_REL = 0.2
# ... on this many tasks of the run (the first task, without the mass feed-forward, is the
# closed loop's transient; a second one is the split's): K_v held from then on (a split that
# came apart once creeps back task by task, each step within the limit)
KV_SPLIT_LATCH = 2
NOTE_KV_SPLIT_HELD = "k_v_split_ill_determined_k_v_held"
# Sensor noise: it enters u through the feedback (white at the sample rate, gain
# sensor_noise_gain of the PD controller), so the fit's residual measures it:
# sigma_n = rms_residual / gain (an upper bound: the model error adds to the residual).
# Through the loop the noise jitters the motor, and the friction (which switches with the
# motor's velocity, not the reference's) is averaged down where the motion is slow: the
# estimate falls about quadratically with the noise (plant_twomass, the demo task: -0.05 %
# at 2e-3 rad, -0.32 % at 5e-3, -0.97 % at 1e-2 beyond the noise-free -0.16 %; make bench,
# bench_track.py "noise"). The jitter's torque against the friction sets how far: the
# relative bias is a function of r = (gain sigma_n) / K_fc (the input's noise rms, which is
# the residual's, over the friction level), about NOISE_BIAS_PER_R2 r^2 (issue 32, third
# pass: with the Coulomb level at 0.5 / 0.7 / 1.0 / 1.4 x plant_twomass's and 1e-2 rad the
# noise's share of the bias was -2.7 / -2.0 / -1.0 / -0.55 %, against r^2's -4.1 / -2.1 /
# -1.0 / -0.5 %; the first model, NOISE_BIAS_PER_RAD2 sigma_n^2 whatever the level, left
# -1.2 % at 0.7 x and -2.8 % at 0.5 x). Its coefficient is the first model's calibration
# point (1 % at 1e-2 rad, r = 2.05, plant_twomass), not refitted; the correction's own size
# is carried as a part of the systematic sigma (its model is measured on one plant and
# task, and over-corrects where r is large: +1.4 % at r = 4.1).
NOISE_BIAS_PER_RAD2 = 100.0
NOISE_CAL_K_FC_V = 0.1157            # the calibration point: plant_twomass's K_fc [V] ...
NOISE_CAL_GAIN_V_PER_RAD = 23.75     # ... and its noise gain (sensor_noise_gain of its PD)
NOISE_BIAS_PER_R2 = NOISE_BIAS_PER_RAD2 * (NOISE_CAL_K_FC_V / NOISE_CAL_GAIN_V_PER_RAD) ** 2
NOTE_NOISE_CORRECTED = "sensor_noise_bias_corrected"
# A viscous change with K_v held: the unconstrained fit's viscous coefficient (weakly
# determined, biased by the K_fc / K_v split, but the bias is the same task to task) is
# watched against its baseline (the median of estimates VISC_BASELINE_FROM ..
# VISC_BASELINE_FROM + VISC_BASELINE_N - 1); a shift beyond VISC_SHIFT_Z times its
# task-to-task scatter and VISC_SHIFT_MIN_REL of the held K_v (or VISC_SHIFT_MIN_ABS) in the
# last two tasks, while K_fc is settled, is a viscous change: the row says so (from then
# on) and K_fc's sigma carries what the change would move it by (the held fit with b at
# K_v + shift, over VISC_SEEN_FRACTION; not applied: the free coefficient sees only part
# of the change, through the split bias).
VISC_BASELINE_FROM = 4
VISC_BASELINE_N = 5
VISC_SHIFT_Z = 4.0
VISC_SHIFT_MIN_REL = 0.25
VISC_SETTLED = 3
# the free coefficient sees about this share of a viscous change (the split bias: 0.83 of
# 1.2 mV s/rad for +60 % on plant_twomass, bench_track.py "viscous drift"): the part is the
# detected shift's effect on K_fc over it
VISC_SEEN_FRACTION = 0.67
VISC_SETTLED_REL = 0.005
VISC_SHIFT_MIN_ABS = 2e-4
NOTE_VISCOUS_CHANGE = "viscous_change_detected"
# A viscous change below the watch's threshold (with sensor noise the free coefficient
# scatters as much as a +60 % change moves it: 0.6 against 0.5 mV s/rad at 1e-2 rad) is
# still folded into K_fc: K_fc's sigma carries, on every task with K_v held, the effect of
# the viscous change the data cannot rule out: the mean shift of the free coefficient over
# the last n tasks (n in VISC_RECENT_N: the longer window resolves a small shift, the
# shorter follows a ramp) from its baseline and that shift's standard error (their
# scatter) in quadrature, the larger of the two, over VISC_SEEN_FRACTION
# (:func:`viscous_unresolved`); the row's ``k_fc_sigma_viscous``.
VISC_RECENT_N = (8, 4)
# tasks whose estimate is within this fraction of the K_fc they ran with (the loop at its
# fixed point): after a Coulomb step the free coefficient jumps for the two tasks the
# feed-forward is wrong (1.5 -> 5.7, 9.8 mV s/rad on plant_twomass), then returns
VISC_FIXED_REL = 0.02
# Friction that falls with speed (a Stribeck rise) shows in the data as a negative viscous
# coefficient of the unconstrained fit (viscous friction alone cannot be negative; on
# plant_twomass +1.5 mV s/rad, with static x2 .. x3 and a Stribeck velocity of 0.05 .. 0.4
# rad/s -3.3 .. -4.7): the median of the last SPEED_WINDOW tasks' (after the first
# VISC_BASELINE_FROM, K_a learnt) below zero names it. K_fc is then the friction the task
# met with its slow phases (K_FC_MEANING), and with a strong rise the estimate falls short
# of it by about a fifth of the rise (docs/track.md), which the sigma does not cover
SPEED_WINDOW = 5
NOTE_FRICTION_FALLS_WITH_SPEED = "friction_falls_with_speed"
# Model error: the model has one inertia term m a_r; the plant's momentum at the moves' ends
# (a two-mass load swinging on through its spring, a motor that sticks late) is not in it,
# and the sign instruments p, n, which step at the moves' ends, read it there fully (issue
# 32, fourth pass: -6 % at 0.3 x plant_twomass's Coulomb level, sigma 0.5 %). The same
# sums give a second estimate with other instruments (:func:`velocity_iv_k_fc`: v_r, which
# is zero at the moves' ends, for the Coulomb level; p - n for the offset; a_r): where the
# model holds the two agree within noise, where it misses they weight the miss differently
# and disagree. Half their gap (the median over the last SCATTER_WINDOW tasks at the loop's
# fixed point, VISC_FIXED_REL, once MODEL_MIN exist: the gap of a task whose feed-forward
# was wrong, the first ones without K_a, a step's, is the closed loop's transient) is a part of
# the systematic sigma (``k_fc_sigma_model``): 2 sigma then reaches the gap, which covers
# the sign estimate's bias wherever the two biases are of opposite sign or the velocity
# instrument's is the larger (docs/track.md, the family "two-mass momentum"). Beyond
# MODEL_NOTE_REL of the floor the row names it.
NOTE_MODEL_ERROR = "model_error_instruments_disagree"
MODEL_NOTE_REL = 1.0
MODEL_MIN = 3               # gaps at the fixed point before their median is the part
# What a task's K_fc is (results.yaml track_summary.k_fc_meaning).
K_FC_MEANING = (
    "the Coulomb friction averaged over the task's path and speeds: the friction the "
    "feed-forward meets where and how fast this task moves, weighted by the time it slides "
    "there (block sums over the repetition); fftune tune reads it over its sine's path (+- the "
    "amplitude around where the axis stands) and speeds, so with friction that depends on "
    "position (run-out, a contaminated stretch) the two differ by the friction's variation "
    "between the two paths, and with a Stribeck rise at low speed it is the friction the "
    "task's own motion meets (higher where the motor slides slowly, the holding torque where "
    "it sticks), above the Coulomb level by what its slow phases add; the sigma covers that "
    "value, not the Coulomb level")


class NotIdentifiable(FftuneError):
    """The task's data cannot determine the estimate; ``cause`` names why (a short key)."""

    def __init__(self, cause, message):
        super().__init__(message)
        self.cause = cause


@dataclass
class TaskStats:
    """One task run's statistics (objects 0x2062 and 0x2061).

    Attributes
    ----------
    repetitions : int
        Recorded repetitions the sums cover.
    samples : int
        Samples per repetition.
    design : ndarray, shape (B, 9)
        Per block: pp nn pv pa nv na vv va aa (float64 of the drive's float32).
    data : ndarray, shape (B, 6)
        Per block: pu nu vu au ee uu.
    """

    repetitions: int
    samples: int
    design: np.ndarray
    data: np.ndarray

    @property
    def blocks(self):
        return self.design.shape[0]

    @property
    def total_samples(self):
        return self.repetitions * self.samples


def _parse(raw, nsums, what):
    raw = bytes(raw)
    if len(raw) < TASK_HEADER_BYTES or (len(raw) - TASK_HEADER_BYTES) % (4 * nsums):
        raise FftuneError(f"task statistics {what}: {len(raw)} bytes is not an 8-byte header plus "
                          f"blocks of {nsums} float32 sums")
    reps, samples = struct.unpack_from("<II", raw, 0)
    vals = np.frombuffer(raw, dtype="<f4", offset=TASK_HEADER_BYTES).astype(np.float64)
    return reps, samples, vals.reshape(-1, nsums)


def parse_task_stats(design_raw, data_raw):
    """The drive's task statistics from the uploads of 0x2062 (design) and 0x2061 (data).

    Raises
    ------
    FftuneError
        Malformed data, parts of different runs, no repetition recorded, non-finite sums.
    """
    r1, n1, design = _parse(design_raw, len(DESIGN_NAMES), "design (0x2062)")
    r2, n2, data = _parse(data_raw, len(DATA_NAMES), "data (0x2061)")
    if design.shape[0] != data.shape[0] or (r1, n1) != (r2, n2):
        raise FftuneError(f"task statistics: design ({r1} repetitions of {n1} samples, {design.shape[0]} blocks) "
                          f"and data ({r2} of {n2}, {data.shape[0]} blocks) do not belong to one run")
    if r1 == 0 or n1 == 0:
        raise FftuneError("task statistics: no repetition recorded (the run did not finish one)")
    for name, arr in (("design", design), ("data", data)):
        bad = ~np.isfinite(arr)
        if bad.any():
            b, k = np.argwhere(bad)[0]
            names = DESIGN_NAMES if name == "design" else DATA_NAMES
            raise FftuneError(f"task statistics {name}: block {b} sum {names[k]} is not finite")
    return TaskStats(repetitions=int(r1), samples=int(n1), design=design, data=data)


def normal_matrix(design_row):
    """The 4 x 4 matrix Phi^T Phi (order p, n, v, a) of one block's design sums."""
    pp, nn, pv, pa, nv, na, vv, va, aa = design_row
    return np.array([[pp, 0.0, pv, pa],
                     [0.0, nn, nv, na],
                     [pv, nv, vv, va],
                     [pa, na, va, aa]])


def _blocks(stats):
    A = np.array([normal_matrix(d) for d in stats.design])
    c = stats.data[:, :4].copy()
    return A, c


@dataclass
class TaskEstimate:
    """Friction (and inertia) estimated from one task run, input-voltage units.

    ``k_fc`` = (F_+ + F_-) / 2 [V]; ``offset`` = (F_+ - F_-) / 2 [V]; ``k_v`` [V s/rad]
    (the held value when ``k_v_identified`` is False); ``k_a`` [V s^2/rad]; sigmas from the
    estimator's sandwich covariance (noise); ``k_fc_sigma`` [V] is
    hypot(``k_fc_sigma_stat``, ``k_fc_sigma_sys``): the sandwich part and the systematic
    floor ``SYS_FLOOR_REL`` |K_fc| (closed-loop fixed point, the stick-slip loop's periodic
    states; measured on the bench, docs/track.md), ``SYS_FLOOR_KV_REL`` |K_fc| when K_v is
    estimated too (the K_fc / K_v split's closed-loop bias). ``rms_error`` [rad] the tracking error,
    ``rms_residual`` [V] of the fit; ``condition`` of the normalised design matrix;
    ``notes`` named limits of this estimate: ``NOTE_VISCOUS_FOLDED`` (K_v held: a viscous
    drift ends up in K_fc, unseparated) or ``NOTE_KV_SPLIT`` (K_v estimated: the split bias);
    ``NOTE_VISCOUS_CHANGE`` (K_v held, a viscous change detected and taken into the fit:
    ``k_v_shift`` [V s/rad]); ``NOTE_NOISE_CORRECTED`` (the sensor noise's bias removed:
    ``k_fc_noise_correction`` [V], from the smallest recent ``sensor_noise_rad``, each task's
    bound rms_residual / noise gain); ``NOTE_FRICTION_FALLS_WITH_SPEED`` (the unconstrained
    fit's viscous coefficient negative over the last SPEED_WINDOW tasks: a Stribeck rise,
    K_fc is the friction the task met, a strong rise not covered). ``k_v_free`` [V s/rad]: the
    viscous coefficient of the unconstrained fit (NaN when the task cannot tell it).
    ``k_fc_sigma_viscous`` [V] (a part of ``k_fc_sigma_sys``, K_v held): what a viscous change
    the tasks cannot rule out moves K_fc by (detected or not; :func:`viscous_unresolved`).
    ``k_fc_instrument_gap`` [V] (K_v held): this task's sign-instrument K_fc (before the noise
    correction) less its velocity-instrument one (:func:`velocity_iv_k_fc`; NaN when K_v is
    estimated or the task cannot give it); ``k_fc_sigma_model`` [V] (a part of
    ``k_fc_sigma_sys``): half the median gap of the recent tasks, the model error the two
    instruments reveal; beyond the floor the row carries ``NOTE_MODEL_ERROR``.
    ``k_fc_sigma_split`` [V] (a part of ``k_fc_sigma_sys``, K_v estimated within a run): the
    four-gain K_fc's gap to the K_v-held fit's at the trusted K_v, less twice the four-gain
    K_fc's sandwich part; ``NOTE_KV_SPLIT_HELD`` when the gap exceeded KV_SPLIT_MAX_REL of
    K_fc (or did on KV_SPLIT_LATCH earlier tasks): the estimate is then the held fit's, K_v
    at the trusted value. ``k_v_trusted`` [V s/rad]: the run's first task's K_v (NaN without
    a run's history).
    """

    k_fc: float
    k_fc_sigma: float
    k_v: float
    k_v_sigma: float
    k_a: float
    k_a_sigma: float
    offset: float
    offset_sigma: float
    rms_error: float
    rms_residual: float
    condition: float
    k_v_identified: bool
    samples: int
    k_fc_sigma_stat: float = 0.0
    k_fc_sigma_sys: float = 0.0
    notes: tuple = ()
    k_v_free: float = math.nan
    k_v_shift: float = 0.0
    sensor_noise_rad: float = math.nan
    k_fc_noise_correction: float = 0.0
    k_fc_sigma_viscous: float = 0.0
    k_fc_applied: float = math.nan
    k_fc_instrument_gap: float = math.nan
    k_fc_sigma_model: float = 0.0
    k_fc_sigma_split: float = 0.0
    k_v_trusted: float = math.nan


def _check_identifiable(A):
    pp, nn, aa = A[0, 0], A[1, 1], A[3, 3]
    if not pp > 0:
        raise NotIdentifiable("no_forward", "the task never moves forward (no sample with a positive "
                                            "reference velocity): Coulomb friction needs both directions")
    if not nn > 0:
        raise NotIdentifiable("no_reversal", "the task never reverses direction (no sample with a negative "
                                             "reference velocity): its Coulomb level cannot be told from a "
                                             "constant load torque; give the task a move back")
    if not aa > 0:
        raise NotIdentifiable("no_acceleration", "the task never accelerates: the inertia cannot be separated")


def _kv_unique_fraction(A):
    """Fraction of v_r's energy not explained by p, n, a_r (1 - R^2 of v on them)."""
    try:
        inv = np.linalg.inv(_normalise(A)[0])
    except np.linalg.LinAlgError:
        return 0.0
    return float(1.0 / inv[2, 2])


def _normalise(A):
    d = np.sqrt(np.clip(np.diag(A), 1e-300, None))
    return A / np.outer(d, d), d


def _solve(A, c, cols):
    sub = np.ix_(cols, cols)
    return np.linalg.solve(A[sub], c[cols])


def velocity_iv_k_fc(A, c, k_v_hold):
    """K_fc [V] from a task's summed sums with the velocity instruments, K_v held.

    The model u - K_v v_r = F_+ p + F_- n + m a_r is written K_fc s + O |s| + m a_r
    (s = p + n the sign, |s| = p - n, K_fc = (F_+ + F_-) / 2, O = (F_+ - F_-) / 2) and
    solved with the instruments z = (v_r, p - n, a_r): Z^T (u - K_v v_r) = Z^T X theta,
    from the drive's sums alone (rows v, p - n, a; columns F_+, F_-, m):

        [[pv, nv, va], [pp, -nn, pa - na], [pa, na, aa]] theta = [vu - K_v vv,
        pu - nu - K_v (pv - nv), au - K_v va]

    (n in {0, -1}: sum n n = nn counts the backward samples, sum (p - n) n = -nn). v_r is zero
    at the moves' ends, where the sign instruments step: the momentum the one inertia term
    does not model (a load swinging on) enters this estimate differently.

    Parameters
    ----------
    A : ndarray, shape (4, 4)
        Phi^T Phi of the task (order p, n, v, a; :func:`normal_matrix` summed).
    c : ndarray, shape (4,)
        Phi^T u (pu, nu, vu, au).
    k_v_hold : float
        The viscous coefficient held [V s/rad].

    Returns
    -------
    float
        K_fc [V]; NaN when the system is singular or not finite.
    """
    A = np.asarray(A, dtype=float)
    c = np.asarray(c, dtype=float)
    if A.shape != (4, 4) or c.shape != (4,):
        raise ValueError(f"velocity_iv_k_fc: A must be 4 x 4 and c of 4 sums, got {A.shape} and {c.shape}")
    pp, nn, pv, nv, pa, na = A[0, 0], A[1, 1], A[0, 2], A[1, 2], A[0, 3], A[1, 3]
    vv, va, aa = A[2, 2], A[2, 3], A[3, 3]
    pu, nu, vu, au = c
    kv = float(k_v_hold)
    M = np.array([[pv, nv, va], [pp, -nn, pa - na], [pa, na, aa]])
    y = np.array([vu - kv * vv, pu - nu - kv * (pv - nv), au - kv * va])
    try:
        th = np.linalg.solve(M, y)
    except np.linalg.LinAlgError:
        return math.nan
    fc = 0.5 * float(th[0] + th[1])
    return fc if math.isfinite(fc) else math.nan


def model_error_sigma(gaps, all_gaps=None):
    """The model-error part of K_fc's sigma [V] from the instrument gaps (sign-instrument K_fc
    less velocity-instrument K_fc, :func:`velocity_iv_k_fc`) of successive tasks (oldest
    first, this task last; NaN for a task left out): half the absolute median of the finite
    ones among the last ``SCATTER_WINDOW``; 0 with fewer than ``MODEL_MIN`` finite ones
    there (the first tasks' gap is the missing mass feed-forward's, not the model's).

    ``all_gaps`` (the same tasks' gaps, none left out): where ``gaps`` leaves out so many
    that fewer than ``MODEL_MIN`` remain among ``SCATTER_WINDOW`` or more tasks (a loop that
    does not settle at a fixed point, or whose estimate scatters beyond the fixed-point
    band), the median of these instead: the loop's persistent state is then what it is."""
    g = np.asarray(gaps, dtype=float)[-SCATTER_WINDOW:]
    g = g[np.isfinite(g)]
    if g.size < MODEL_MIN and all_gaps is not None and len(all_gaps) >= SCATTER_WINDOW:
        g = np.asarray(all_gaps, dtype=float)[-SCATTER_WINDOW:]
        g = g[np.isfinite(g)]
    if g.size < MODEL_MIN:
        return 0.0
    return 0.5 * abs(float(np.median(g)))


def scatter_sigma(values):
    """Standard deviation of one estimate from a series of successive ones (newest last),
    insensitive to a linear drift and to a single jump: from the successive differences d,
    1.4826 median |d - median d| / sqrt(2). None with fewer than ``SCATTER_MIN`` values."""
    x = np.asarray(values, dtype=float)
    if x.size < SCATTER_MIN:
        return None
    d = np.diff(x[-SCATTER_WINDOW:])
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))


def sensor_noise_gain(kp, kd, tau_d_s, fs_hz):
    """rms of the controller output u (V) per rad of white sensor noise: the PD of the drive
    (firmware_sim/core/ctl.h: u = kp e + D, D = p D' + g (e - e'), g = kd / (tau_d + ts),
    p = tau_d / (tau_d + ts)), impulse response kp + g, then g (p - 1) p^(k-1):
    sqrt((kp + g)^2 + g^2 (1 - p) / (1 + p))."""
    ts = 1.0 / float(fs_hz)
    den = float(tau_d_s) + ts
    g, p = float(kd) / den, float(tau_d_s) / den
    return math.sqrt((float(kp) + g) ** 2 + g ** 2 * (1.0 - p) / (1.0 + p))


def noise_bias_rel(r):
    """The sensor noise's bias of K_fc relative to it, as a correction (positive): r the noise's
    rms at the plant input (gain sigma_n, V) over K_fc; NOISE_BIAS_PER_R2 r^2."""
    return NOISE_BIAS_PER_R2 * float(r) ** 2


def viscous_shift(k_v_free, k_v_hold, k_fc=None, latched=False):
    """The change of the plant's viscous coefficient seen by the unconstrained fit, from the
    free estimates of the tasks so far (oldest first, this one last): (shift, detected).

    The baseline is the median of the estimates VISC_BASELINE_FROM .. + VISC_BASELINE_N - 1
    (not the first tasks: K_a is still learnt), its noise the scatter of the estimates
    after it (or of the baseline's); detected when the last two estimates both differ from
    the baseline by more than max(VISC_SHIFT_Z x that scatter, VISC_SHIFT_MIN_REL |K_v|,
    VISC_SHIFT_MIN_ABS) on the same side; the shift is then the median of the last two
    minus the baseline (0 when not detected). Only while K_fc is settled: its last
    VISC_SETTLED estimates (``k_fc``, oldest first, this one last) within VISC_SETTLED_REL of
    their median; while K_fc is wrong (a Coulomb step, a drift) the closed loop moves the
    free viscous coefficient too, and that is no viscous change. ``latched`` (a change was
    detected before): the shift is reported whatever its size (a change persists; noise
    would make the detection flicker)."""
    x = np.asarray([v for v in k_v_free], dtype=float)
    need = VISC_BASELINE_FROM + VISC_BASELINE_N + 2
    if x.size < need or not np.all(np.isfinite(x[VISC_BASELINE_FROM:])):
        return 0.0, False
    base = float(np.median(x[VISC_BASELINE_FROM:VISC_BASELINE_FROM + VISC_BASELINE_N]))
    if latched:
        return float(np.median(x[-2:]) - base), True
    if k_fc is not None:
        f = np.asarray(k_fc, dtype=float)[-VISC_SETTLED:]
        med = float(np.median(f)) if f.size else 0.0
        if f.size < VISC_SETTLED or not np.all(np.abs(f - med) <= VISC_SETTLED_REL * abs(med)):
            return 0.0, False
    base_win = x[VISC_BASELINE_FROM:VISC_BASELINE_FROM + VISC_BASELINE_N]
    base = float(np.median(base_win))
    d = np.diff(base_win)
    scat = float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))
    thr = max(VISC_SHIFT_Z * scat, VISC_SHIFT_MIN_REL * abs(float(k_v_hold)), VISC_SHIFT_MIN_ABS)
    last = x[-2:] - base
    if np.all(np.abs(last) > thr) and np.sign(last[0]) == np.sign(last[1]):
        return float(np.median(x[-2:]) - base), True
    return 0.0, False


def viscous_unresolved(k_v_free, fixed_point=None):
    """The viscous change [V s/rad] the free coefficient's estimates (oldest first, this task
    last) cannot rule out, as the free fit sees it: the mean of the last n minus the
    baseline (the median of estimates VISC_BASELINE_FROM .. + VISC_BASELINE_N - 1) and the
    standard error of that difference added in quadrature, the largest over n in
    ``VISC_RECENT_N``, from their task-to-task scatter
    (:func:`scatter_sigma` of those after the baseline's first). Values not finite or not at
    the fixed point are left out; 0 before the baseline and one more task exist, or with
    fewer than two usable values."""
    x = np.asarray([v for v in k_v_free], dtype=float)
    end = VISC_BASELINE_FROM + VISC_BASELINE_N
    if x.size < end + 1:
        return 0.0
    if fixed_point is not None:   # the closed loop away from its fixed point moves it
        ok = np.asarray(fixed_point, dtype=bool)
        if ok.size == x.size:
            x = np.where(ok, x, np.nan)
    base_win = x[VISC_BASELINE_FROM:end]
    base_win = base_win[np.isfinite(base_win)]
    if base_win.size < 2:
        return 0.0
    base = float(np.median(base_win))
    d = np.diff(x[VISC_BASELINE_FROM:])
    d = d[np.isfinite(d)]
    if d.size < 2:
        return 0.0
    scat = float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0))
    out = 0.0
    for n in VISC_RECENT_N:
        recent = x[-n:]
        recent = recent[np.isfinite(recent)]
        if recent.size == 0:
            continue
        se = scat * math.sqrt(1.0 / recent.size + 1.0 / base_win.size)
        out = max(out, math.hypot(float(np.mean(recent)) - base, se))
    return out


def _at_fixed_point(applied, estimate):
    """Whether a task ran with the feed-forward at its estimate (within VISC_FIXED_REL; True
    when the applied value is not known)."""
    if applied is None or not math.isfinite(applied):
        return True
    return abs(applied - estimate) <= VISC_FIXED_REL * abs(estimate)


def estimate_task(stats, k_v_hold=0.0, cond_limit=COND_LIMIT, kv_unique_min=KV_UNIQUE_MIN, hold_k_v=False,
                  recent_k_fc=(), noise_gain=None, recent=None, k_fc_applied=None):
    """Estimate K_fc (and K_v, K_a) with sigmas from one task run's statistics.

    Parameters
    ----------
    stats : TaskStats
    k_v_hold : float
        K_v [V s/rad] assumed when the task does not excite the viscous term separately from
        the Coulomb one (its velocity is nearly +-constant): the estimate then fixes b there.
    cond_limit : float
        Largest condition number of the correlation-normalised design matrix accepted.
    kv_unique_min : float
        Least fraction of v_r's energy not explained by p, n, a_r for estimating K_v.
    hold_k_v : bool
        Fix b at ``k_v_hold`` whatever the task (K_v not tracked).
    recent_k_fc : sequence of float
        K_fc estimates [V] of the previous tasks (oldest first). With at least
        ``SCATTER_MIN`` - 1 of them the statistical part of ``k_fc_sigma`` is their scatter
        with this one (:func:`scatter_sigma`); before that it is the sandwich's, which takes
        the residual as white and overstates the noise of a closed loop (its residual is
        mostly high-frequency feedback of sensor noise, the slow regressors see little of it).
    noise_gain : float or None
        rms of u per rad of sensor noise (:func:`sensor_noise_gain` of the drive's PD): the
        sensor noise is then read from the residual and its bias removed
        (:func:`noise_bias_rel` of the input's noise rms over K_fc); None: not corrected.
    recent : sequence of TaskEstimate or None
        The previous tasks' estimates (oldest first). With K_v held a change of the viscous
        friction is then watched (:func:`viscous_shift` on their ``k_v_free``), and the
        sensor noise is the smallest of their residual bounds and this one's over the last
        ``SCATTER_WINDOW`` tasks (a model error, e.g. while a gain is still wrong, only
        adds to a residual; with no earlier task no correction). With K_v estimated the
        split is checked against the held fit at the trusted K_v (the first estimate's
        ``k_v_trusted``, or ``k_v_hold`` on the run's first task, ``recent`` empty).
        None: none of these.
    k_fc_applied : float or None
        The K_fc [V] the drive ran this task with: a task whose estimate differs from it by
        more than VISC_FIXED_REL (the loop away from its fixed point: the closed loop moves
        the free viscous coefficient) is left out of :func:`viscous_unresolved`.

    Returns
    -------
    TaskEstimate

    Raises
    ------
    NotIdentifiable
        The task cannot determine K_fc (never reverses, never moves forward, collinear
        regressors, fewer samples than parameters); ``cause`` names it.
    """
    A_b, c_b = _blocks(stats)
    A, c = A_b.sum(axis=0), c_b.sum(axis=0)
    _check_identifiable(A)
    kv_unique = _kv_unique_fraction(A) >= kv_unique_min
    kv_ok = not hold_k_v and kv_unique
    recent = list(recent) if recent is not None else None
    split_gap, split_held = 0.0, False
    # the trusted K_v: the one the first task of the run ran with (carried by the estimates)
    k_v_ref = float(k_v_hold)
    if recent and math.isfinite(recent[0].k_v_trusted):
        k_v_ref = float(recent[0].k_v_trusted)
    # the split's conditioning: the four-gain K_fc against the held fit's at the trusted K_v
    if kv_ok and recent is not None:
        try:
            fc4 = 0.5 * sum(_solve(A, c, [0, 1, 2, 3])[:2])
            fch = 0.5 * sum(_solve(A, c - k_v_ref * A[:, 2], [0, 1, 3])[:2])
            split_gap = float(fc4 - fch)
        except np.linalg.LinAlgError:
            split_gap = math.inf
        latched = sum(NOTE_KV_SPLIT_HELD in e.notes for e in (recent or [])) >= KV_SPLIT_LATCH
        if latched or not math.isfinite(split_gap) or abs(split_gap) > KV_SPLIT_MAX_REL * abs(fch):
            kv_ok, split_held, split_gap = False, True, 0.0
            k_v_hold = k_v_ref
    cols = [0, 1, 2, 3] if kv_ok else [0, 1, 3]
    k_v_free = math.nan
    if kv_unique:
        try:
            k_v_free = float(_solve(A, c, [0, 1, 2, 3])[2])
        except np.linalg.LinAlgError:
            k_v_free = math.nan
    k_v_shift, shifted = 0.0, False
    k_v_unresolved = 0.0
    recent = list(recent) if recent is not None else None
    if not kv_ok and recent is not None:
        fc_now = 0.5 * sum(_solve(A, c - k_v_hold * A[:, 2], [0, 1, 3])[:2])
        k_v_unresolved = viscous_unresolved(
            [e.k_v_free for e in recent] + [k_v_free],
            [_at_fixed_point(e.k_fc_applied, e.k_fc - e.k_fc_noise_correction) for e in recent]
            + [_at_fixed_point(k_fc_applied, fc_now)])
        fc_free_held = 0.5 * sum(_solve(A, c - k_v_hold * A[:, 2], cols)[:2])
        k_v_shift, shifted = viscous_shift([e.k_v_free for e in recent] + [k_v_free], k_v_hold,
                                           [e.k_fc - e.k_fc_noise_correction for e in recent]
                                           + [fc_free_held],
                                           latched=bool(recent) and NOTE_VISCOUS_CHANGE in recent[-1].notes)
    gap = math.nan
    if not kv_ok:   # the velocity instruments' K_fc against the sign instruments' (model error)
        fc_v = velocity_iv_k_fc(A, c, k_v_hold)
        fc_s = 0.5 * sum(_solve(A, c - k_v_hold * A[:, 2], [0, 1, 3])[:2])
        gap = float(fc_s - fc_v) if math.isfinite(fc_v) else math.nan
    if not kv_ok:  # u - b v_r on p, n, a_r
        c_shift = c - (k_v_hold + k_v_shift) * A[:, 2]
        c = c - k_v_hold * A[:, 2]
        c_b = c_b - k_v_hold * A_b[:, :, 2]
    An, _ = _normalise(A[np.ix_(cols, cols)])
    cond = float(np.linalg.cond(An))
    if not np.isfinite(cond) or cond > cond_limit:
        raise NotIdentifiable("collinear", f"the task's regressors are nearly collinear (condition number "
                                           f"{cond:.3g} > {cond_limit:.3g}): the friction terms cannot be separated")
    theta = np.zeros(4)
    theta[cols] = _solve(A, c, cols)
    shift_effect = 0.0
    if not kv_ok:
        theta[2] = k_v_hold
        # K_fc per V s/rad of viscous coefficient in the held fit
        g_b = _solve(A, A[:, 2], cols)
        g_fc = 0.5 * float(g_b[0] + g_b[1])
        if shifted:   # how far the detected shift would move K_fc: a part of its sigma
            th_shift = _solve(A, c_shift, cols)
            shift_effect = 0.5 * (th_shift[0] + th_shift[1]) - 0.5 * (theta[0] + theta[1])
        # and the change the data cannot rule out (detected or not)
        shift_effect = max(abs(shift_effect), abs(g_fc * k_v_unresolved))
    n = stats.total_samples
    k = len(cols)
    # residual sum of squares per block, u - Phi theta (theta with the held K_v: the
    # residual of the fit actually made), from the block's sums alone
    c_o = stats.data[:, :4]
    uu_b = stats.data[:, 5]
    rss_b = uu_b - 2.0 * c_o @ theta + np.einsum("i,bij,j->b", theta, A_b, theta)
    resid2 = max(0.0, float(uu_b.sum() - 2.0 * theta @ c_o.sum(axis=0) + theta @ A @ theta))
    rss_b = np.clip(rss_b, 0.0, None)
    if n <= k:
        raise NotIdentifiable("too_few_samples", f"{n} samples for {k} parameters: no uncertainty can be given")
    # instrumental-variable (here least-squares, Z = Phi) asymptotic covariance, sandwich
    # form with a residual variance per block (heteroscedastic between the phases of the
    # motion, white within a block):  V = A^-1 (sum_b s2_b A_b) A^-1,
    # s2_b = RSS_b / n_b * n / (n - k)  (n_b the block's samples; dof of the whole fit)
    n_b = _block_samples(stats)
    s2_b = rss_b / n_b * (n / (n - k))
    sub = np.ix_(cols, cols)
    A_inv = np.linalg.inv(A[sub])
    meat = np.einsum("b,bij->ij", s2_b, A_b[:, cols][:, :, cols])
    V = np.zeros((4, 4))
    V[sub] = A_inv @ meat @ A_inv
    w_fc = np.array([0.5, 0.5, 0.0, 0.0])
    w_off = np.array([0.5, -0.5, 0.0, 0.0])
    fc = 0.5 * (theta[0] + theta[1])
    fc_stat = math.sqrt(max(0.0, float(w_fc @ V @ w_fc)))
    fc_sys = (SYS_FLOOR_REL if not kv_ok else SYS_FLOOR_KV_REL) * abs(float(fc))
    notes = [NOTE_KV_SPLIT] if kv_ok else [NOTE_VISCOUS_FOLDED if not shifted else NOTE_VISCOUS_CHANGE]
    if split_held:
        notes.append(NOTE_KV_SPLIT_HELD)
    # the sensor noise, read from the residual, and its bias
    sigma_n, corr = math.nan, 0.0
    if noise_gain:
        sigma_n = math.sqrt(resid2 / n) / float(noise_gain)
        bounds = [e.sensor_noise_rad for e in (recent or [])[-(SCATTER_WINDOW - 1):]
                  if math.isfinite(e.sensor_noise_rad)]
        if bounds and fc != 0.0:   # a bound confirmed by another task (the first tasks' residual is model error)
            r = float(noise_gain) * min([sigma_n] + bounds) / abs(float(fc))
            corr = noise_bias_rel(r) * float(fc)
        fc = fc + corr
        if abs(corr) > 0.1 * SYS_FLOOR_REL * abs(fc):
            notes.append(NOTE_NOISE_CORRECTED)
    # the scatter of the estimates as reported (the earlier ones are corrected too)
    scat = scatter_sigma(list(recent_k_fc) + [fc])
    if scat is not None:
        fc_stat = scat
    fc_visc = abs(shift_effect) / VISC_SEEN_FRACTION
    floor = fc_sys
    # the gaps of the tasks at the loop's fixed point (a task whose feed-forward was wrong,
    # after a step or while K_a is learnt, has the closed loop's transient in its gap)
    all_gaps = [e.k_fc_instrument_gap for e in (recent or [])] + [gap]
    fixed = [_at_fixed_point(e.k_fc_applied, e.k_fc - e.k_fc_noise_correction) for e in (recent or [])] \
        + [_at_fixed_point(k_fc_applied, fc - corr)]
    fc_model = model_error_sigma([g if ok else math.nan for g, ok in zip(all_gaps, fixed)], all_gaps) \
        if math.isfinite(gap) else 0.0
    if fc_model > MODEL_NOTE_REL * floor:
        notes.append(NOTE_MODEL_ERROR)
    # the gap less what the noise alone makes of it (the four-gain K_fc's sandwich part,
    # twice: the held fit is nested in it, so the gap's noise is at most the four-gain's)
    fc_split = max(0.0, abs(split_gap) - 2.0 * math.sqrt(max(0.0, float(w_fc @ V @ w_fc))))
    fc_sys = math.sqrt(fc_sys ** 2 + corr ** 2 + fc_visc ** 2 + fc_model ** 2 + fc_split ** 2)
    if recent is not None and len(recent) >= VISC_BASELINE_FROM + SPEED_WINDOW - 1:
        kv_seen = [e.k_v_free for e in recent[-(SPEED_WINDOW - 1):]] + [k_v_free]
        if all(math.isfinite(v) for v in kv_seen) and float(np.median(kv_seen)) < 0.0:
            notes.append(NOTE_FRICTION_FALLS_WITH_SPEED)
    notes = tuple(notes)
    return TaskEstimate(
        k_fc=float(fc), k_fc_sigma=math.hypot(fc_stat, fc_sys),
        k_v=float(theta[2]), k_v_sigma=float(math.sqrt(max(0.0, V[2, 2]))) if kv_ok else 0.0,
        k_a=float(theta[3]), k_a_sigma=float(math.sqrt(max(0.0, V[3, 3]))),
        offset=float(0.5 * (theta[0] - theta[1])), offset_sigma=math.sqrt(max(0.0, float(w_off @ V @ w_off))),
        rms_error=math.sqrt(max(0.0, float(stats.data[:, 4].sum())) / n),
        rms_residual=math.sqrt(resid2 / n),
        condition=cond, k_v_identified=bool(kv_ok), samples=n,
        k_fc_sigma_stat=fc_stat, k_fc_sigma_sys=fc_sys, notes=notes,
        k_v_free=k_v_free, k_v_shift=float(k_v_shift), sensor_noise_rad=sigma_n,
        k_fc_noise_correction=float(corr), k_fc_sigma_viscous=float(fc_visc),
        k_fc_applied=math.nan if k_fc_applied is None else float(k_fc_applied),
        k_fc_instrument_gap=gap, k_fc_sigma_model=float(fc_model), k_fc_sigma_split=float(fc_split),
        k_v_trusted=k_v_ref if recent is not None else math.nan)


def _block_samples(stats):
    """Samples per block over the recorded repetitions (the drive cuts a repetition of N
    samples into B blocks at b N // B, as firmware_sim/core/task.c)."""
    B, N = stats.blocks, stats.samples
    edges = np.array([(b * N) // B for b in range(B + 1)])
    return np.maximum(np.diff(edges), 1) * stats.repetitions


# ---- the tracking policy ----------------------------------------------------------------

TREND_TASKS = 3            # successive changes of the estimate that make a trend
TREND_MIN_Z = 3.0          # their mean beyond this many times the estimate's scatter
TREND_MIN_SHARE = 0.5      # each change at least this share of their mean ...
TREND_NOISE_Z = 2.0        # ... less this many times a change's noise
TREND_KEEP_Z = 2.0         # a trend already seen continues while its mean is beyond this


def curvature_scatter(values):
    """Standard deviation of one estimate from a series (newest last), insensitive to a
    drift that bends slowly (an exponential approach) and to a single jump: from the second
    differences c of the last ``SCATTER_WINDOW`` values, 1.4826 median |c - median c| / sqrt 6
    (white noise of std s gives second differences of std s sqrt 6). None with fewer than
    ``SCATTER_MIN`` + 1 values."""
    x = np.asarray(values, dtype=float)[-SCATTER_WINDOW:]
    if x.size < SCATTER_MIN + 1:
        return None
    c = np.diff(x, 2)
    return float(1.4826 * np.median(np.abs(c - np.median(c))) / math.sqrt(6.0))


def drift_trend(estimates, scatter_floor=0.0, active=False, min_rate=0.0):
    """The drift per task [V] of a series of K_fc estimates (newest last), or 0.

    A trend is TREND_TASKS successive changes d of one sign, each at least TREND_MIN_SHARE
    of their mean m less TREND_NOISE_Z times a change's noise (sqrt 2 times the estimate's
    scatter s, :func:`curvature_scatter`, at least ``scatter_floor``: a noisy estimate
    makes one change of a drift small), with |m| above TREND_MIN_Z s (a step of the
    friction gives one or two changes, the mixed task and the next, then none: no trend).
    ``active`` (the last update had a trend): it continues while |m| > TREND_KEEP_Z s,
    without the share rule (a noisy estimate would make the trend flicker, and each lost
    task lags by the drift's rate). Either way |m| must exceed ``min_rate`` [V per task] (the
    tracker: TREND_TASKS changes within the systematic floor are the loop's own settling,
    e.g. its fixed point relaxing after a ramp's end, not a drift of the friction).
    Its value is their mean m (the noise of one change would be extrapolated), or the last
    change where that is smaller and of the same sign (0 where of the other sign: a drift
    that slows, an exponential's tail, is led by its present rate, and a noisy early change
    does not extend the lead; issue 32's third pass), unless the
    last change falls short of the mean of the ones before by more than TREND_NOISE_Z times
    the noise of that difference (the drift slows or stops: an exponential's tail, a ramp's
    end, whose last change is its partial task): then the last change times its ratio to
    that mean (within 0 .. 1), a rate that decays as the changes do."""
    x = np.asarray(estimates, dtype=float)
    if x.size < TREND_TASKS + 1 or not np.all(np.isfinite(x[-(TREND_TASKS + 1):])):
        return 0.0
    d = np.diff(x[-(TREND_TASKS + 1):])
    m = float(np.mean(d))
    noise = curvature_scatter(x)
    if noise is None or m == 0.0:
        return 0.0
    s = max(noise, float(scatter_floor))
    if not abs(m) > float(min_rate):
        return 0.0
    sg = math.copysign(1.0, m)
    tol = TREND_NOISE_Z * math.sqrt(2.0) * s
    if active:   # a trend seen before continues while its mean change stands out
        if not abs(m) > TREND_KEEP_Z * s:
            return 0.0
    elif not (np.all(d * sg >= TREND_MIN_SHARE * abs(m) - tol) and abs(m) > TREND_MIN_Z * s):
        return 0.0
    before = float(np.mean(d[:-1]))
    # var(d_last - mean(before)) for white estimates: 2 + 2 / (n - 1) + 2 (n - 2) / (n - 1) ... ~ (2 + 1) s^2
    if (before - d[-1]) * sg > TREND_NOISE_Z * math.sqrt(3.0) * s:
        return float(d[-1] * min(1.0, max(0.0, float(d[-1] / before))))
    return sg * min(abs(m), max(0.0, float(d[-1]) * sg))


@dataclass
class TrackSettings:
    """Limits of the tracking policy (docs/track.md; ``track:`` keys of the configuration).

    max_step_rel, max_step_abs : K_fc may change per update by at most
        max(max_step_rel K_fc, max_step_abs) [V].
    kv_max_step : largest K_v change per update [V s/rad].
    ka_max_step_rel : largest K_a change per update relative to K_a (no limit while K_a = 0).
    gain : fraction of the estimated correction applied (1: all of it).
    rollback_ratio : the tracking error rms of the task after an update above this times
        the one before it (and above rollback_min_rms_rad) undoes the update, if that update
        changed K_fc by more than rollback_min_step_rel of it (a smaller change cannot
        explain the growth: the friction itself moved).
    max_rollbacks : consecutive rollbacks before stopping.
    max_sigma_rel : K_fc's sigma above this fraction of K_fc holds K_fc (K_a is still
        updated if its sigma is within ka_max_sigma_rel of it: the mass feed-forward is what a
        first task without it lacks most); max_uncertain such tasks in a row stop.
    rms_limit_rad : tracking error rms above this stops (safety).
    update_kv : track K_v where the task identifies it.
    trend_lead_tasks : a drift faster than the task-to-task scatter, seen as TREND_TASKS
        successive changes of the estimate in one direction and of similar size, is
        extrapolated by this many tasks (a task's estimate is its average; the next task ends
        1.5 tasks later); 0: no trend term.
    """

    max_step_rel: float = 0.25
    max_step_abs: float = 0.005
    kv_max_step: float = 0.005
    ka_max_step_rel: float = 0.5
    gain: float = 1.0
    rollback_ratio: float = 2.0
    rollback_min_rms_rad: float = 1e-3
    rollback_min_step_rel: float = 0.05
    max_rollbacks: int = 3
    max_sigma_rel: float = 0.2
    ka_max_sigma_rel: float = 0.5
    max_uncertain: int = 5
    rms_limit_rad: float = 0.5
    update_kv: bool = True
    trend_lead_tasks: float = 1.5


@dataclass
class Decision:
    """What to do after a task: ``action`` 'update', 'hold', 'rollback' or 'stop'; the gains to
    apply next; ``cause`` a short key and ``reason`` a sentence (stops, rollbacks, holds)."""

    action: str
    k_fc: float
    k_v: float
    k_a: float
    cause: str = ""
    reason: str = ""


def _bounded(old, new, limit):
    step = new - old
    if limit is not None and abs(step) > limit:
        step = math.copysign(limit, step)
    return old + step


@dataclass
class Tracker:
    """Bounded task-by-task updates of K_fc, K_v, K_a with rollback and named stops.

    Call :meth:`after_task` with each task's estimate (or the NotIdentifiable it raised);
    it returns the :class:`Decision` for the next task. State: the gains in effect, those
    before the last update and the tracking error then.
    """

    k_fc: float
    k_v: float
    k_a: float
    settings: TrackSettings = field(default_factory=TrackSettings)
    _prev: tuple = None
    _prev_rms: float = None
    _last_action: str = "start"
    _rollbacks: int = 0
    _uncertain: int = 0
    _estimates: list = field(default_factory=list)
    _trend: bool = False

    def _stop(self, cause, reason):
        self._last_action = "stop"
        return Decision("stop", self.k_fc, self.k_v, self.k_a, cause, reason)

    def after_task(self, est):
        """The decision after one task (est: TaskEstimate or NotIdentifiable)."""
        s = self.settings
        if isinstance(est, NotIdentifiable):
            return self._stop(est.cause, str(est))
        if not math.isfinite(est.rms_error) or est.rms_error > s.rms_limit_rad:
            return self._stop("tracking_error", f"tracking error rms {est.rms_error:.3g} rad above the limit "
                                                f"{s.rms_limit_rad:g} rad")
        if (self._last_action == "update" and self._prev_rms is not None
                and abs(self.k_fc - self._prev[0]) > s.rollback_min_step_rel * max(self._prev[0], 1e-12)
                and est.rms_error > s.rollback_ratio * self._prev_rms
                and est.rms_error > s.rollback_min_rms_rad):
            self._rollbacks += 1
            if self._rollbacks >= s.max_rollbacks:
                return self._stop("rollbacks", f"{self._rollbacks} updates in a row raised the tracking error "
                                               f"(last: rms {est.rms_error:.3g} rad after {self._prev_rms:.3g} rad)")
            self.k_fc, self.k_v, self.k_a = self._prev
            self._last_action = "rollback"
            return Decision("rollback", self.k_fc, self.k_v, self.k_a, "error_grew",
                            f"tracking error rms {est.rms_error:.3g} rad > {s.rollback_ratio:g} x "
                            f"{self._prev_rms:.3g} rad before the last update: its gains restored")
        fc_certain = est.k_fc_sigma <= s.max_sigma_rel * max(abs(est.k_fc), 1e-12)
        ka_certain = est.k_a_sigma <= s.ka_max_sigma_rel * max(abs(est.k_a), 1e-12)
        if not fc_certain:
            self._uncertain += 1
            if self._uncertain >= s.max_uncertain:
                why = (f" (its model misses: the sign and velocity instruments' estimates differ, "
                       f"model-error part {est.k_fc_sigma_model:.3g} V; the load's momentum at the moves' "
                       f"ends, which one inertia term does not model)" if NOTE_MODEL_ERROR in est.notes else "")
                return self._stop("uncertain", f"K_fc {est.k_fc:.4g} V with sigma {est.k_fc_sigma:.3g} V "
                                               f"(> {s.max_sigma_rel:.0%} of it) in {self._uncertain} tasks "
                                               f"in a row: the task's data cannot tell it{why}")
        else:
            self._uncertain = 0
        if self._last_action != "rollback":
            self._rollbacks = 0
        self._prev = (self.k_fc, self.k_v, self.k_a)
        self._prev_rms = est.rms_error
        if not fc_certain:  # hold K_fc (and K_v); the inertia may still be learnt
            if ka_certain:
                lim_ka = s.ka_max_step_rel * self.k_a if self.k_a > 0 else None
                self.k_a = max(0.0, _bounded(self.k_a, self.k_a + s.gain * (est.k_a - self.k_a), lim_ka))
            self._last_action = "hold"
            return Decision("hold", self.k_fc, self.k_v, self.k_a, "uncertain",
                            f"K_fc sigma {est.k_fc_sigma:.3g} V > {s.max_sigma_rel:.0%} of {est.k_fc:.4g} V: held")
        lim_fc = max(s.max_step_rel * self.k_fc, s.max_step_abs)
        self._estimates.append(float(est.k_fc))
        trend = drift_trend(self._estimates, active=self._trend,
                            min_rate=SYS_FLOOR_REL * abs(est.k_fc) / TREND_TASKS) * s.trend_lead_tasks
        self._trend = bool(trend)
        target = self.k_fc + s.gain * (est.k_fc + trend - self.k_fc)
        self.k_fc = max(0.0, _bounded(self.k_fc, target, lim_fc))
        if trend:
            self._last_action = "update"
            self._update_kv_ka(est)
            return Decision("update", self.k_fc, self.k_v, self.k_a, "trend",
                            f"K_fc drifts by {trend / s.trend_lead_tasks:+.3g} V per task: the update "
                            f"leads the estimate by {s.trend_lead_tasks:g} tasks ({trend:+.3g} V)")
        self._update_kv_ka(est)
        self._last_action = "update"
        return Decision("update", self.k_fc, self.k_v, self.k_a)

    def _update_kv_ka(self, est):
        s = self.settings
        if s.update_kv and (est.k_v_identified or NOTE_KV_SPLIT_HELD in est.notes):
            # the split ill-determined: K_v back to the trusted value the estimate held it at
            self.k_v = max(0.0, _bounded(self.k_v, self.k_v + s.gain * (est.k_v - self.k_v), s.kv_max_step))
        lim_ka = s.ka_max_step_rel * self.k_a if self.k_a > 0 else None
        self.k_a = max(0.0, _bounded(self.k_a, self.k_a + s.gain * (est.k_a - self.k_a), lim_ka))
