"""The drive's task generator (firmware_sim/core/task.c, through libfwsim.so) pinned on
every branch of its 7-segment design (issue 33: the survivors of its mutation run): the
repetition's sample count against the time-optimal jerk-limited profile computed here
(float64, the textbook durations rounded up to whole samples), and the recorded set-point
against the limits and the distance. Unequal limits: v_max reached or not, a_max reached
or not, the acceleration phase shortened, the pure-jerk move of a tiny distance, limits
below 1 (a slow axis).
"""
import math

import numpy as np
import pytest

from track_sim import TWOMASS, FwSim

FS = 2560.0


def samples(dur_s):
    """Whole samples of a duration, rounded up (an exact count within float noise stays)."""
    x = dur_s * FS
    k = math.floor(x)
    return k + 1 if k < x - 1e-4 * max(x, 1.0) else k


def optimal_segments(d, v, a, j):
    """(branch, t_j, t_a, t_v) of the time-optimal rest-to-rest move over d (s): jerk phases
    t_j, constant-acceleration phases t_a, the constant-velocity phase t_v."""
    if v * j < a * a:                       # v_max reached before a_max: a = sqrt(v j)
        tj, ta = math.sqrt(v / j), 0.0
    else:
        tj, ta = a / j, v / a - a / j
    d_acc = v * (2 * tj + ta)               # the distance to reach v_max and stop again
    if d >= d_acc:
        return "cruise", tj, ta, (d - d_acc) / v
    # no cruise: d = A (2 tj^2 + 3 tj ta + ta^2) at the acceleration A = j tj kept
    A = j * tj
    ta = 0.5 * (-3 * tj + math.sqrt(tj * tj + 4 * d / A))
    if ta > 0:
        return "short", tj, ta, 0.0
    return "jerk only", (d / (2 * j)) ** (1 / 3), 0.0, 0.0   # d = 2 j tj^3


CASES = [  # distance, v_max, a_max, jerk, dwell, branch
    (0.7, 3.0, 30.0, 600.0, 0.25, "cruise"),
    (0.37, 2.2, 17.0, 450.0, 0.11, "cruise"),
    (0.7, 0.5, 30.0, 600.0, 0.05, "cruise"),       # a_max not reached
    (0.9, 0.3, 0.6, 0.9, 0.07, "cruise"),          # a slow axis: every limit below 1
    (0.2, 3.0, 30.0, 600.0, 0.13, "short"),
    (0.01, 3.0, 30.0, 600.0, 0.09, "jerk only"),
    (0.013, 2.2, 17.0, 450.0, 0.3, "jerk only"),
    (0.15, 1.0, 0.1, 0.05, 0.2, "jerk only"),      # t_j^3 = 1.5 s^3: the cube root of more than 1
]


def _run(sim, mode, d, v, a, j, dwell):
    sim.configure(task_mode=mode, exc_kind=0, exc_settle_periods=0, exc_record_periods=1,
                  rec_signals=0x13, task_distance=d, task_v_max=v, task_a_max=a, task_jerk=j,
                  task_dwell=dwell)
    sim.enable()
    sim.start()
    sim.run_until_idle()
    data, names = sim.record()
    return data[:, names.index("reference")].astype(np.float64)


@pytest.mark.parametrize("d, v, a, j, dwell, branch", CASES)
def test_task_repetition_is_the_time_optimal_move_in_whole_samples(d, v, a, j, dwell, branch):
    got_branch, tj, ta, tv = optimal_segments(d, v, a, j)
    assert got_branch == branch                 # (the case covers the branch it names)
    nj, na, nv, nd = max(1, samples(tj)), samples(ta), samples(tv), samples(dwell)
    move = 4 * nj + 2 * na + nv
    for mode, reps in ((1, 2), (2, 1)):        # back and forth; forward only
        with FwSim(TWOMASS) as sim:
            sim.set("KFC", 0.1)
            r = _run(sim, mode, d, v, a, j, dwell)
            n = int(sim.get("TASK_PERIOD"))
            assert n == reps * (move + nd), (mode, n, nj, na, nv, nd)
            r = r - r[0]
            assert r.size == n
            assert r.max() == pytest.approx(d, abs=2e-6 * max(1.0, d))     # exactly d (float32)
            vel = np.diff(r) * FS
            # (the mean acceleration over 16 samples: the float32 set-point's rounding,
            # differentiated twice per sample, would exceed a slow axis' a_max)
            acc = (r[32:] - 2 * r[16:-16] + r[:-32]) * (FS / 16) ** 2
            # the whole-sample durations are longer than the optimum: lower v, a, j
            assert np.abs(vel).max() <= v * (1 + 1e-3)
            assert np.abs(acc).max() <= a * (1 + 1e-2)
            # the dwell at d: nd samples (and the move before it: its last sample reaches d)
            at_d = np.flatnonzero(np.abs(r - d) < 2e-6 * max(1.0, d))
            assert at_d.size >= nd and at_d[0] <= move + 1
            if mode == 2:
                assert vel.min() >= -1e-3 * v           # forward: never backward


@pytest.mark.parametrize("bad", [dict(task_distance=0.0), dict(task_v_max=0.0), dict(task_a_max=0.0),
                                 dict(task_jerk=0.0)])
def test_task_without_a_design_has_no_repetition(bad):
    """A zero limit or distance: no design (a repetition of 0 samples), not a move."""
    with FwSim(TWOMASS) as sim:
        params = dict(task_distance=0.2, task_v_max=2.0, task_a_max=20.0, task_jerk=500.0, task_dwell=0.1)
        params.update(bad)
        sim.configure(task_mode=1, exc_kind=0, exc_settle_periods=0, exc_record_periods=1,
                      rec_signals=0x13, **params)
        assert int(sim.get("TASK_PERIOD")) == 0
