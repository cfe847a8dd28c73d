"""Checks of the assumptions an estimate rests on, made before anything is averaged.

The robust BLA averages periods and realizations, the HOSIDF averages blocks and repeats.
Both assume that every block they average carries the same excitation (periodic steady
state, one realization per group, one level), at the claimed layout. :func:`check_blocks`
checks the excitation (input u, or the reference r) block by block against the others,
before any averaging, and either refuses in one line naming the real cause and where
(record, block, sample, level) or handles it (blocks without excitation at the end or
the start dropped, realization boundaries inferred from the phases of the input
spectrum, realizations that share one excitation taken as periods of one) and says so
in a note. :func:`check_arguments` is the one argument check of every BLA and HOSIDF
entry function.

Every estimator calls these: :func:`fftune.analysis.bla.robust_bla` (and with it
:func:`~fftune.analysis.bla.bla_levels` and ``fftune analyze bla``) and
:func:`fftune.analysis.hosidf.hosidf` (``fftune analyze hosidf``, which also splits
repeats at different amplitudes into levels with :func:`amplitude_levels`).
"""
from dataclasses import dataclass, field

import numpy as np

from fftune.analysis.errors import InputError

__all__ = ["BlockLayout", "check_arguments", "check_blocks", "amplitude_levels",
           "locate_nonfinite"]

# thresholds (dB re the median block of the record, or re its median level)
DEAD_DB = -20.0          # a block this far under the median carries no excitation
STEP_DB = 1.0            # a block's level off by more: a level step / partial block
STEP_MIN_DB = 0.2        # a step between consecutive blocks that stays (and 10x their scatter)
GROUP_DB = {"multisine": 1.5, "sine": 0.5}   # realizations / repeats at one level
SAME_CORR = 0.9          # consecutive blocks this correlated at the lines: the same
NEW_CORR = 0.5           # under this: a different excitation (new phases)
TIME_SCREEN = 0.3        # rms(block - mean) / rms(mean) under this: periodic, no FFT


def check_arguments(*, fs, n_period=None, settle_periods=None, n_total=None, hold_text=True):
    """The argument check shared by every BLA and HOSIDF entry function.

    Parameters
    ----------
    fs : float
        Sample rate (Hz): finite and > 0.
    n_period : int, optional
        Samples per period (block) N: >= 4.
    settle_periods : int, optional
        T: 0 <= T < ``n_total``.
    n_total : int, optional
        Periods per realization T + P in the data.
    hold_text : bool
        Say in the message how many periods the data hold.

    Returns
    -------
    (float, int or None)
        fs and T as numbers.

    Raises
    ------
    InputError
    """
    try:
        fs_value = float(fs)
    except (TypeError, ValueError):
        raise InputError(f"fs must be a positive sample rate in Hz, got {fs!r}") from None
    if not np.isfinite(fs_value) or fs_value <= 0:
        raise InputError(f"fs must be a positive sample rate in Hz, got {fs}")
    if n_period is not None and int(n_period) < 4:
        raise InputError(f"samples per period N = {n_period} is too small")
    settle = None
    if settle_periods is not None:
        settle = int(settle_periods)
        if n_total is not None and not 0 <= settle < n_total:
            raise InputError(f"settle periods T = {settle} must be in 0 .. {n_total - 1}"
                             + (f" (the data hold {n_total} periods per realization)"
                                if hold_text else ""))
        if settle < 0:
            raise InputError(f"settle periods T = {settle} must be >= 0")
    return fs_value, settle


@dataclass
class BlockLayout:
    """What :func:`check_blocks` found and how the blocks are to be taken.

    Attributes
    ----------
    index : ndarray of int, shape (M', T' + P')
        Per new group (realization / repeat) the blocks to use, as indices into the
        blocks of the record in order (``x.reshape(-1, N)``).
    settle_periods : int
        T' of the new layout (blocks at the start of each new group not averaged).
    notes : list of str
        What was handled and how (empty on clean data).
    changed : bool
        ``index`` differs from the layout given.
    levels : ndarray, shape (M',)
        rms of each new group's excitation (its kept blocks).
    mean_spectrum : ndarray of complex, shape (M', N // 2 + 1), or None
        ``rfft`` of each new group's mean over its kept blocks (when computed).
    """

    index: np.ndarray
    settle_periods: int
    notes: list = field(default_factory=list)
    changed: bool = False
    levels: np.ndarray = None
    mean_spectrum: np.ndarray = None

    def apply(self, a):
        """The array ``a`` (shaped like the checked one, (G, B, N)) in the new layout."""
        a = np.asarray(a)
        if not self.changed:
            return a
        flat = a.reshape(-1, a.shape[-1])
        return flat[self.index]


def _rms_blocks(flat):
    """rms of every row of a (K, N) array (float64 accumulation)."""
    if flat.dtype == np.float64:
        return np.sqrt(np.einsum("kn,kn->k", flat, flat) / flat.shape[1])
    # (other types: block by block, no float64 copy of the whole record)
    return np.sqrt(np.array([np.dot(b.astype(np.float64), b.astype(np.float64))
                             for b in flat]) / flat.shape[1])


def _db(x):
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(np.maximum(x, 1e-300))


def _first_above(block, thr):
    hit = np.flatnonzero(np.abs(block) > thr)
    return int(hit[0]) if hit.size else block.size


def _last_above(block, thr):
    hit = np.flatnonzero(np.abs(block) > thr)
    return int(hit[-1]) + 1 if hit.size else 0


def check_blocks(x, *, kind="multisine", settle_periods=0, name="input u", group="realization",
                 block="period", fs=None, infer=True, mixed_levels="refuse",
                 want_mean_spectrum=False):
    """Check, before averaging, that every block of every group carries the same
    excitation, and say how the blocks are to be taken.

    Per block (in the order recorded) the excitation's level (rms) is compared with
    the median block: blocks 20 dB or more under it carry no excitation, blocks off by
    more than 1 dB a different level. Per group the blocks after the settle blocks
    must then be alike:

    * no excitation (or a partial block) at the end: the excitation stops (a burst):
      those blocks are dropped and a note names the sample where it stops; at the
      start: it starts late, likewise. In the middle: a gap, refused naming it.
    * a level that changes within the group and stays: a level step, refused naming
      the block, the sample and both levels.
    * a group without any excitation: dropped (a note names it).
    * groups at different levels (sorted levels with a step of more than 1.5 dB for a
      multisine, 0.5 dB for a sine, :func:`amplitude_levels`):
      refused (``mixed_levels="refuse"``) naming the levels, kept with a note
      (``"note"``), or kept (``"keep"``: the caller splits them with
      :func:`amplitude_levels`).

    Then the waveform: when a block differs from its group's mean by more than 0.3 of
    its rms (a periodic input with little noise never does), the spectra of the blocks
    at their strongest lines are compared: consecutive blocks of one excitation
    correlate (> 0.9); new phases (< 0.5) mark a realization boundary. Boundaries at
    regular intervals are taken as the realizations they are (a note says so; with
    ``infer=False`` refused); a shifted copy (the same lines, a phase that grows with
    the frequency) is an excitation that does not repeat every N samples (refused,
    naming the shift); no correlation at all: not periodic with this N (refused).
    Finally (multisine) groups whose mean spectra correlate (> 0.9) share one
    excitation: one-period groups are taken as periods of one realization, longer ones
    get a note (their spread is noise only).

    Parameters
    ----------
    x : array_like, shape (G, B, N)
        The excitation (u, or r) of G groups (realizations or repeats) of B blocks
        (periods) of N samples.
    kind : {'multisine', 'sine'}
        A sine's repeats share their phase by design: not merged.
    settle_periods : int
        Blocks T at the start of each group that the estimate does not average (not
        level-checked; kept in the index).
    name, group, block : str
        Words for the messages ("input u", "realization", "period").
    fs : float, optional
        Sample rate (Hz), for times in the messages.
    infer : bool
        Take realization boundaries found from the data (else refuse, naming them).
    mixed_levels : {'refuse', 'note', 'keep'}
        Groups at different levels: refused, kept with a note, kept silently (the
        caller splits them).
    want_mean_spectrum : bool
        Also return the spectrum of every group's mean over its kept blocks in the new
        layout (``BlockLayout.mean_spectrum``; float64 records): the one the checks
        compute anyway for realizations, which the line finder then reuses.

    Returns
    -------
    BlockLayout

    Raises
    ------
    InputError
        The real cause and where.
    """
    x = np.asarray(x)
    if x.ndim != 3:
        raise InputError(f"{name}: expected an array shaped ({group}s, {block}s, samples), "
                         f"got shape {x.shape}")
    n_groups, n_blocks, n = x.shape
    settle = int(settle_periods)
    flat = x.reshape(-1, n)
    index = np.arange(n_groups * n_blocks).reshape(n_groups, n_blocks)
    # one realization at a time (its blocks stay in cache): the blocks' levels, and for
    # the waveform screen below the mean of its kept blocks and their products with it
    pre = None
    if x.dtype == np.float64 and n_blocks - settle >= 2 and 0 <= settle:
        level = np.empty(n_groups * n_blocks)
        pre_mean = np.empty((n_groups, n))
        pre_dots = np.empty((n_groups, n_blocks - settle))
        for g in range(n_groups):
            xg = x[g]
            level[g * n_blocks:(g + 1) * n_blocks] = np.einsum("bn,bn->b", xg, xg)
            pre_mean[g] = np.add.reduce(xg[settle:], axis=0) / (n_blocks - settle)
            pre_dots[g] = np.einsum("bn,n->b", xg[settle:], pre_mean[g])
        level = np.sqrt(level / n)
        pre = (pre_mean, pre_dots)
    else:
        level = _rms_blocks(flat)
    if not np.all(np.isfinite(level)):
        return BlockLayout(index=index, settle_periods=settle)     # the estimator refuses
    kept = index[:, settle:].reshape(-1)
    ref = float(np.median(level[kept]))
    if not ref > 0:
        return BlockLayout(index=index, settle_periods=settle)
    rel_db = _db(level / ref)
    dead = rel_db <= DEAD_DB
    notes = []
    changed = False

    def at(k, offset=0):
        s = int(k) * n + offset
        return f"sample {s}" + (f" ({s / fs:.4g} s)" if fs else "")

    def where(k):
        g, b = divmod(int(k), n_blocks)
        return f"{group} {g}, {block} {b}" if n_groups > 1 else f"{block} {b}"

    # --- per group: dead and partial blocks, level steps ------------------------------
    starts = np.full(n_groups, settle)
    stops = np.full(n_groups, n_blocks)
    amp_cache = []

    def amp_ref():
        """Where the excitation starts or stops: the first / last sample over 2 % of the
        blocks' median peak, and over 4 times the rms of the blocks without excitation."""
        if not amp_cache:
            peak = float(np.median(np.max(np.abs(flat[kept]), axis=1)))
            floor = float(np.median(level[dead])) if dead.any() else 0.0
            amp_cache.append(max(0.02 * peak, 4.0 * floor))
        return amp_cache[0]

    dropped_groups = []
    # (all groups at once: the medians of their kept blocks; a group whose blocks are
    # all alive and within STEP_DB of its median needs nothing more)
    kept_lv = level[index[:, settle:]]
    med_g = np.median(kept_lv, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        quiet = ~(dead[index[:, settle:]].any(axis=1)
                  | (np.abs(_db(kept_lv / med_g[:, None])) > STEP_DB).any(axis=1))
    if quiet.any() and n_blocks - settle >= 2:
        _level_step(level, index[quiet][:, settle:], name, where, at, block)
    for g in np.flatnonzero(~quiet):
        ks = index[g, settle:]
        live = ~dead[ks]
        if not live.any():
            dropped_groups.append(g)
            continue
        # steps re the group's own level (groups at different levels: checked below)
        ref_g = float(med_g[g]) if live.all() else float(np.median(level[ks[live]]))
        rel_g = _db(level[ks] / ref_g)
        bad = dead[ks] | (np.abs(rel_g) > STEP_DB)
        if not bad.any():
            continue
        good = np.flatnonzero(~bad)
        if good.size == 0:
            steps = np.flatnonzero(np.abs(_db(level[ks[1:]] / level[ks[:-1]])) > STEP_DB)
            if steps.size == 1:
                k = ks[steps[0] + 1]
                raise InputError(
                    f"{name}: the excitation level changes at {where(k)} ({at(k)}): "
                    f"{_db(level[k] / level[k - 1]).item():+.1f} dB (rms {level[k - 1]:.4g} -> "
                    f"{level[k]:.4g}) and stays: {block}s at different levels cannot be "
                    f"averaged; record each level on its own")
            raise InputError(f"{name}: no {block} of {group} {g} at a common level (levels "
                             f"{rel_g.min():+.1f} .. {rel_g.max():+.1f} dB re its median, from "
                             f"{at(ks[0])}): the level changes {block} by {block}")
        # blocks off the level because the input was clipped: named as such
        off_lv = ks[bad & ~dead[ks]]
        clip = _clipped(flat, off_lv, ks[~bad])
        if clip is not None:
            k, limit, count = clip
            raise InputError(
                f"{name}: the excitation is clipped at +-{limit:.4g} in {where(k)} ({at(k)}) "
                f"and {int(off_lv.size) - 1} other {block}(s) off the level of the rest "
                f"({count} samples at the limit in that one): a saturated input (an output "
                f"limit) changes the level and the spectrum of those {block}s; lower the "
                f"excitation level or cut them out")
        first, last = good[0], good[-1]
        inner = bad[first:last + 1]
        if inner.any():
            k = ks[first + np.flatnonzero(inner)[0]]
            kd = ks[first:last + 1][inner]
            if dead[kd].any():
                kk = kd[dead[kd]]
                stop = _last_above(flat[kk[0] - 1], amp_ref()) if kk[0] > ks[0] else 0
                raise InputError(
                    f"{name}: a gap in the excitation: none from {at(kk[0] - 1, stop)} "
                    f"({where(kk[0])}) for {kk.size} {block}(s), then it resumes: the "
                    f"{block}s around it are not one steady state; cut the record at the gap")
            before = float(np.median(level[ks[:first + np.flatnonzero(inner)[0]]]))
            raise InputError(
                f"{name}: the excitation level changes at {where(k)} ({at(k)}): "
                f"{_db(level[k] / before).item():+.1f} dB (rms {before:.4g} -> "
                f"{level[k]:.4g}), {int(inner.sum())} {block}(s) off the level of the others: "
                f"blocks at different levels cannot be averaged; record each level on its own")
        # leading or trailing blocks only: a late start / a burst that ends
        lead, trail = first, bad.size - 1 - last
        # a level that steps and stays (two levels in one group) is not a burst: the
        # blocks after the step are not dead
        for count, side in ((trail, "end"), (lead, "start")):
            if not count:
                continue
            sel = ks[last + 1:] if side == "end" else ks[:first]
            edge, rest = (sel[0], sel[1:]) if side == "end" else (sel[-1], sel[:-1])
            if not (dead[rest].all() and level[edge] < ref_g):
                # the step: from the last block of one level to the first of the other
                k = sel[0] if side == "end" else sel[-1] + 1
                other = "after" if side == "end" else "before"
                raise InputError(
                    f"{name}: the excitation level changes at {where(k)} ({at(k)}): "
                    f"{_db(level[k] / level[k - 1]).item():+.1f} dB (rms {level[k - 1]:.4g} "
                    f"-> {level[k]:.4g}), {count} {block}(s) {other} it at the other level: "
                    f"{block}s at different levels cannot be averaged; record each level on "
                    f"its own")
            if side == "end":
                k = sel[0]
                stop = _last_above(flat[k], amp_ref())
                notes.append(f"{name}: the excitation stops at {at(k, stop)} ({where(k)}): "
                             f"the last {count} {block}(s) of {group} {g} carry no or partial "
                             f"excitation and are dropped (a burst shorter than the record)"
                             if n_groups > 1 else
                             f"{name}: the excitation stops at {at(k, stop)} ({where(k)}): "
                             f"the last {count} {block}(s) carry no or partial excitation and "
                             f"are dropped (a burst shorter than the record)")
                stops[g] = settle + last + 1
            else:
                k = sel[-1]
                start = _first_above(flat[k], amp_ref())
                notes.append(f"{name}: the excitation starts at {at(k, start)} ({where(k)}): "
                             f"the first {count} {block}(s) after the settle {block}s carry "
                             f"no or partial excitation and are dropped")
                starts[g] = settle + first
        changed = True
    keep_groups = [g for g in range(n_groups) if g not in dropped_groups]
    if dropped_groups:
        if not keep_groups:
            raise InputError(f"{name}: no excitation in any {group}")
        notes.append(f"{name}: {group}(s) {_ranges(dropped_groups)} carry no excitation "
                     f"(20 dB or more under the others from {at(index[dropped_groups[0], 0])}): "
                     f"dropped")
        changed = True
    # every group keeps the same number of blocks (the estimators' layout): the count
    # that keeps the most blocks (groups with fewer are dropped; ties: more groups)
    avail = (stops - starts)[keep_groups]
    count = max(sorted(set(avail.tolist())), key=lambda c: (c * int(np.sum(avail >= c)),
                                                             int(np.sum(avail >= c))))
    short = [g for g, a in zip(keep_groups, avail) if a < count]
    if short:
        notes.append(f"{name}: {group}(s) {_ranges(short)} dropped (fewer {block}s left than "
                     f"the others: {count} kept in each)")
        keep_groups = [g for g in keep_groups if g not in short]
    if changed:
        index = np.stack([np.concatenate((index[g, :settle],
                                          index[g, starts[g]:starts[g] + count]))
                          for g in keep_groups])
        if np.any((stops - starts)[keep_groups] > count) and len(keep_groups) > 1:
            notes.append(f"{count} {block}(s) kept in every {group} (the same number in each)")
    n_groups = index.shape[0]
    # --- groups at different levels --------------------------------------------------
    glev = np.median(level[index[:, settle:]], axis=1)
    tol = GROUP_DB.get(kind, 1.5)
    groups = amplitude_levels(glev, tol_db=tol) if n_groups > 1 else [np.arange(n_groups)]
    if len(groups) > 1 and mixed_levels != "keep":
        text = (f"the {group}s are at {len(groups)} different levels (rms "
                + ", ".join(f"{glev[gs].mean():.3g}" for gs in groups[:6])
                + (" ..." if len(groups) > 6 else "")
                + f"; {group}s " + "; ".join(_ranges(gs) for gs in groups[:6]) + ")")
        if mixed_levels == "refuse":
            raise InputError(f"{name}: {text}: averaging them gives a level that none had; "
                             f"analyse each level on its own (the CLI's hosidf splits them)")
        notes.append(f"{name}: {text}: the BLA of a nonlinear system depends on the level, "
                     f"and this one averages them (bla_levels analyses each level on its own)")
    # --- waveform: the same excitation in every kept block -------------------------
    screen_means = None
    sub = x[:, settle:] if not changed else flat[index[:, settle:]]      # (G, P', N)
    if sub.shape[1] >= 2:
        # |x_b - mean|^2 = |x_b|^2 - 2 <x_b, mean> + |mean|^2 (no copy)
        if pre is not None and not changed:
            mean, dots = pre
        else:
            mean, dots = np.add.reduce(sub, axis=1, dtype=np.float64) / sub.shape[1], None
        screen_means = (index.copy(), mean)
        m2 = np.einsum("gn,gn->g", mean, mean)
        x2 = (level[index[:, settle:]] ** 2) * n
        if dots is not None:
            pass
        elif sub.dtype == np.float64:
            dots = np.einsum("gbn,gn->gb", sub, mean)
        else:           # (one group at a time: no float64 copy of the whole record)
            dots = np.stack([sub[g].astype(np.float64) @ mean[g] for g in range(sub.shape[0])])
        dev2 = np.maximum(x2 - 2 * dots + m2[:, None], 0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            screen = np.sqrt(dev2 / m2[:, None])
        if not np.all(screen < TIME_SCREEN):
            index, settle_new, note, moved = _waveform(flat, index, settle, n_blocks, name,
                                                       group, block, kind, fs, infer, at)
            if note:
                notes.append(note)
            if moved:
                changed = True
                settle = settle_new
    # --- groups that share one excitation (multisine realizations) ----------------
    mean_spectrum = None

    def group_means():
        # those of the screen when the layout stayed, else one group at a time (no copy
        # of the record)
        if screen_means is not None and np.array_equal(screen_means[0], index):
            return screen_means[1]
        return np.stack([np.add.reduce(flat[index[g, settle:]], axis=0,
                                       dtype=np.float64) / (index.shape[1] - settle)
                         for g in range(index.shape[0])])
    if kind == "multisine" and index.shape[0] >= 2:
        mean_spectrum = np.fft.rfft(group_means(), axis=-1)
        lines, spec = _strong_lines(mean_spectrum)
        if lines.size >= 2:
            c = _corr(spec[:-1], spec[1:])
            if np.all(c.real > SAME_CORR):
                m = index.shape[0]
                same = (f"{name}: the {m} {group}s share one excitation (their spectra at the "
                        f"{lines.size} strongest lines correlate, {c.real.min():.3f} or more)")
                if index.shape[1] - settle == 1:
                    notes.append(f"{same}: they are {block}s of one {group}, taken as such "
                                 f"(1 x {m * index.shape[1]} {block}s; a {group} needs its own "
                                 f"random phases)")
                    index = index.reshape(1, -1)
                    changed = True
                    mean_spectrum = None
                else:
                    notes.append(f"{same}: not independent {group}s (a {group} needs its own "
                                 f"random phases), so the spread over them is noise only: the "
                                 f"total and nonlinear variances say nothing about distortion")
    if mean_spectrum is None and want_mean_spectrum and index.shape[1] > settle \
            and x.dtype == np.float64:
        mean_spectrum = np.fft.rfft(group_means(), axis=-1)
    levels = np.median(level[index[:, settle:]], axis=1)
    return BlockLayout(index=index, settle_periods=settle, notes=notes, changed=changed,
                       levels=levels, mean_spectrum=mean_spectrum)


def _at_peak(row):
    """Samples of a block at its largest |value| (within 1e-9 of it), and that value."""
    a = np.abs(row)
    top = float(a.max())
    return int(np.sum(a >= top * (1.0 - 1e-9))), top


def _clipped(flat, blocks, others):
    """The first of ``blocks`` (indices into the rows of ``flat``) whose largest |value|
    is held by 3 or more samples and by 4 times as many as in the median block of
    ``others`` (a limit, where a waveform that repeats reaches its peak as often in
    every block), as (block, limit, samples at the limit), or None."""
    if not len(blocks) or not len(others):
        return None
    usual = float(np.median([_at_peak(flat[int(k)])[0] for k in others]))
    for k in blocks:
        count, top = _at_peak(flat[int(k)])
        if top > 0 and count >= 3 and count >= 4 * usual:
            return int(k), top, count
    return None


def _level_step(level, ks, name, where, at, block):
    """A level that steps between two consecutive blocks by less than STEP_DB re the
    median (half the blocks at each level: each 0.5 dB off it) and stays: the step
    from one block to the next against the scatter of the blocks' levels. Refused when
    it exceeds STEP_MIN_DB and 10 times that scatter (the robust standard deviation of
    the steps between consecutive blocks, over every group) and the blocks on each
    side (two or more) agree among themselves within a third of it."""
    lv = _db(level[ks])                                   # (G, B)
    d = np.diff(lv, axis=1)
    flat = d.reshape(-1)
    scatter = 1.4826 * float(np.median(np.abs(flat - np.median(flat))))
    thr = max(STEP_MIN_DB, 10.0 * scatter)
    for g, b in zip(*np.nonzero(np.abs(d) > thr)):
        before, after = lv[g, :b + 1], lv[g, b + 1:]
        # (at least 2 blocks on each side: one block off at the start is a transient
        # the estimator handles, one at the end a partial block)
        if before.size >= 2 and after.size >= 2 and np.ptp(before) <= abs(d[g, b]) / 3 \
                and np.ptp(after) <= abs(d[g, b]) / 3:
            k = ks[g, b + 1]
            raise InputError(
                f"{name}: the excitation level changes at {where(k)} ({at(k)}): "
                f"{d[g, b]:+.1f} dB (rms {level[k - 1]:.4g} -> {level[k]:.4g}) and stays "
                f"(the {before.size} {block}(s) before and {after.size} after agree within "
                f"{max(np.ptp(before), np.ptp(after)):.2g} dB; steps from {block} to {block} "
                f"scatter by {scatter:.2g} dB): {block}s at different levels cannot be "
                f"averaged; record each level on its own")


def _ranges(idx):
    idx = list(int(i) for i in idx)
    if len(idx) > 2 and idx == list(range(idx[0], idx[-1] + 1)):
        return f"{idx[0]}..{idx[-1]}"
    return ",".join(str(i) for i in idx[:8]) + (",..." if len(idx) > 8 else "")


def _strong_lines(spec, top=128):
    """The strongest lines of (K, L) spectra (power summed over K; DC left out): those
    within 10 dB of the strongest, at most ``top``. Returns (lines, spec[:, lines])."""
    power = np.sum(np.abs(spec) ** 2, axis=0)
    power[0] = 0.0
    if power.max(initial=0.0) <= 0:
        return np.array([], dtype=np.int64), spec[:, :0]
    order = np.argsort(power)[::-1]
    lines = order[power[order] > 0.1 * power[order[0]]][:top]
    lines.sort()
    return lines, spec[:, lines]


def _corr(a, b):
    """Complex correlation of the rows of a and b: sum a conj(b) / sqrt(sum|a|^2 sum|b|^2)."""
    num = np.sum(a * np.conj(b), axis=-1)
    den = np.sqrt(np.sum(np.abs(a) ** 2, axis=-1) * np.sum(np.abs(b) ** 2, axis=-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def _waveform(flat, index, settle, n_blocks, name, group, block, kind, fs, infer, at):
    """Blocks that differ in waveform: compare consecutive blocks' spectra at the
    strongest lines. Returns (index, settle, note, moved) or raises."""
    n = flat.shape[1]
    n_groups = index.shape[0]
    blocks = index.reshape(-1)
    spec = np.fft.rfft(flat[blocks], axis=-1)             # (G B', L)
    lines, s = _strong_lines(spec)
    if lines.size == 0:
        return index, settle, None, False
    per = index.shape[1]
    s = s.reshape(n_groups, per, -1)
    c = _corr(s[:, :-1], s[:, 1:])                        # (G, B' - 1)
    # only the kept blocks (after the settle blocks) must be alike; a boundary may fall
    # anywhere
    kept_c = c[:, settle:] if settle < per - 1 else c[:, :0]
    if kept_c.size == 0 or np.all(kept_c.real > SAME_CORR):
        return index, settle, None, False
    mag = np.abs(c)
    # a shifted copy: the same lines, |c| high, a phase that grows with frequency
    if np.all(mag[:, settle:] > SAME_CORR):
        g, b = np.unravel_index(np.argmin(kept_c.real), kept_c.shape)
        b = b + settle
        # the shift of every block re the one before (all pairs at once): one shift
        # throughout is a period that is not N; a shift that changes steadily is a
        # frequency that drifts
        a0, a1 = s[:, settle:-1], s[:, settle + 1:]
        phase = np.unwrap(np.angle(a1 * np.conj(a0)), axis=-1)
        w = np.abs(a0) * np.abs(a1)
        shifts = -(np.sum(w * lines * phase, axis=-1) / np.sum(w * lines * lines, axis=-1)
                   * n / (2 * np.pi))                               # (G, B' - 1 - T)
        shift = float(shifts[g, b - settle])
        what = ("the sine is off the DFT grid of the blocks" if kind == "sine" else
                "the excitation does not repeat every N samples")
        sg = shifts[g]
        if sg.size >= 3:
            steps = np.diff(sg)
            spread = float(sg.max() - sg.min())
            if spread > max(0.5, 0.2 * float(np.abs(sg).max())) and \
                    (np.all(steps > 0) or np.all(steps < 0)):
                period = n + sg
                raise InputError(
                    f"{name}: the excitation's frequency drifts: the period moves steadily "
                    f"from {period[0]:.6g} to {period[-1]:.6g} samples over {block}s "
                    f"{settle}..{settle + sg.size} of {group} {g} (N = {n}; the shift "
                    f"between consecutive {block}s grows from {sg[0]:+.3g} to {sg[-1]:+.3g} "
                    f"samples): no N holds whole periods; lock the generator to the sample "
                    f"clock, or analyse shorter stretches")
        raise InputError(
            f"{name}: {what}: {block} {b + 1} of {group} {g} is the one before shifted by "
            f"{shift:+.3g} samples (N = {n}: the period would be {n + shift:.6g} samples, "
            f"or the {block}s are not whole periods); give N = the period, or record an "
            f"integer number of periods per {block}")
    new = c.real < NEW_CORR
    same = c.real > SAME_CORR
    if np.all(new[:, settle:]):
        period = _find_period(flat[index.reshape(-1)].reshape(-1), n, max_samples=4 * n)
        raise InputError(
            f"{name}: the excitation does not repeat every N = {n} samples (consecutive "
            f"{block}s correlate at most {c.real.max():.2f} at the {lines.size} strongest "
            f"lines)" + (f": the record repeats every {period} samples; give N = {period}"
                         if period else ": no period found in the record, not a periodic "
                         "excitation"))
    if not new.any():
        # no new phases anywhere, only periods less alike than a clean periodic input's:
        # noise on the input (a measured current, a loop's feedback), said, not refused
        g, b = np.unravel_index(np.argmin(c.real), c.shape)
        return index, settle, (f"{name}: its {block}s differ more than a clean periodic "
                               f"excitation's ({block}s {b} and {b + 1} of {group} {g} "
                               f"correlate {c[g, b].real:.2f} at the {lines.size} strongest "
                               f"lines): noise on the input, which biases the BLA (errors in "
                               f"the input); give the reference r if there is one"), False
    # boundaries: new phases between consecutive blocks of a group
    bounds = [np.flatnonzero(new[g]) + 1 for g in range(n_groups)]
    runs = [np.diff(np.concatenate(([0], bd, [per]))) for bd in bounds]
    length = int(runs[0][0])
    regular = all(np.all(r == length) for r in runs) and length > max(settle, 1)
    first = next(((g, int(bd[0])) for g, bd in enumerate(bounds) if bd.size), (0, 0))
    k0 = index[first[0], first[1]]
    listing = ", ".join(str(int(b)) for b in bounds[first[0]][:6]) + \
        (" ..." if bounds[first[0]].size > 6 else "")
    if not regular or not infer:
        raise InputError(
            f"{name}: the excitation changes its phases at {block}s {listing} of "
            f"{group} {first[0]} (from {at(k0)}): these are different realizations, not "
            f"{block}s of one; give the number of realizations (--realizations M, or the "
            f"layout (M, T+P, N))")
    m_new = n_groups * (per // length)
    new_index = index.reshape(m_new, length)
    note = (f"{name}: the excitation changes its phases every {length} {block}s ({block}s "
            f"{listing} of {group} {first[0]}, from {at(k0)}): taken as M = {m_new} "
            f"realizations of {length} {block}s, the first {settle} of each not averaged "
            f"(give --realizations M to say so)")
    return new_index, settle, note, True


def _find_period(x, n, max_samples=1 << 16):
    """The lag in N/2 .. 3N/2 at which the record best repeats (normalized
    autocorrelation over 0.9), or None."""
    x = np.asarray(x[:max_samples], dtype=np.float64)
    x = x - x.mean()
    hi = min(3 * n // 2, x.size // 2)
    if hi <= n // 2:
        return None
    f = np.fft.rfft(x, 2 * x.size)
    ac = np.fft.irfft(np.abs(f) ** 2)[:hi + 1]
    lags = np.arange(n // 2, hi + 1)
    norm = ac[lags] / (ac[0] * (x.size - lags) / x.size)
    best = int(np.argmax(norm))
    return int(lags[best]) if norm[best] > 0.9 else None


def amplitude_levels(levels, tol_db=0.5):
    """Group repeats by level: sorted levels split where consecutive ones differ by
    more than ``tol_db``.

    Parameters
    ----------
    levels : array_like, shape (R,)
        Per repeat a level (rms or amplitude, > 0).
    tol_db : float

    Returns
    -------
    list of ndarray of int
        Repeat indices of each level, by ascending level (each in recorded order).
    """
    lv = np.asarray(levels, dtype=float).reshape(-1)
    order = np.argsort(lv, kind="stable")
    steps = _db(lv[order][1:] / lv[order][:-1])
    cuts = np.flatnonzero(steps > tol_db) + 1
    return [np.sort(part) for part in np.split(order, cuts)]


def locate_nonfinite(name, x, *, group="realization", block="period", fs=None):
    """The one-line message for a record holding NaN or inf, naming where: the first
    such sample (group, block, sample index in the record and in seconds) and how many
    samples and blocks are affected. None when every sample is finite.

    Parameters
    ----------
    name : str
        The signal ("input u").
    x : array_like, shape (G, B, N)
    group, block : str
        Words for the messages.
    fs : float, optional
        Sample rate (Hz), for the time.
    """
    x = np.asarray(x)
    bad = ~np.isfinite(x)
    if not bad.any():
        return None
    g_n, b_n, n = x.shape
    first = int(np.flatnonzero(bad.reshape(-1))[0])
    g, rest = divmod(first, b_n * n)
    b, k = divmod(rest, n)
    blocks = int(bad.any(axis=-1).sum())
    at = f"sample {rest}" + (f" ({rest / fs:.4g} s)" if fs else "")
    where = (f"{group} {g}, {block} {b}" if g_n > 1 else f"{block} {b}")
    return (f"{name}: contains NaN or inf: {int(bad.sum())} sample(s) in {blocks} {block}(s), "
            f"the first at {where} ({at} of the {group if g_n > 1 else 'record'}); cut the "
            f"record there or repair the samples")
