"""Tune's uncertainty budget and bias over plant families (issue 22): `fftune tune`'s
experiment logic (fftune.host.experiments.tune) on the firmware core + plant through ctypes
(tests/fwsim_drive.py: the same C controller and plant as drive_sim, no CANopen), on
variants of configs/plant_twomass.yaml x noise seeds.

Families (values chosen here; the method is built for the family, not the values):
strong stiction with a Stribeck curve (Coulomb x8), coarse encoders (128-512 counts) with
noise, Coulomb asymmetry up to 0.4, stiff shafts with load-side damping, heavy motor
inertia, u_max near and below the Coulomb level, tiny friction (Coulomb x0.05), and the
demo plant with noise.

Prints per row: true Coulomb level, K_fc*, error, sigma_total (and its parts), experiments,
converged or the named cause; per family: coverage (truth within 2 sigma_total), rows
within 2 %, median experiments; then the acceptance: no converged row with
|K_fc* - truth| > max(2 %, 2 sigma_total), u_max rows unconverged with the cause named,
median experiments <= 6; then the coverage over 15 noise seeds on the demo plant and an
asymmetric one. Runs with raw samples (rows printed) and with the drive's line statistics
(summary); `--capture raw|stats` one of them, `--fast` the subset tests/test_tune_search.py
uses, `--hidden` the reviewer's families of issue 32 on values the rows above do not have
(hidden_families: 98 rows, rows and per-family coverage printed, no lag map or seed loop).
"""
import os
import statistics
import sys
import tempfile

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir))
sys.path.insert(0, os.path.join(REPO, "tests"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import bench_tune  # noqa: E402

FC0 = bench_tune.FC0            # plant_twomass.yaml Coulomb torque [N m] (0.1157 V)


def _plant(**kw):
    out = {}
    for k, v in kw.items():
        section = "sensor" if k in ("counts_per_rev", "noise_std", "seed") else \
            "controller" if k == "u_max" else "plant"
        out.setdefault(section, {})[k] = v
    return out


def families():
    """{family: [(row name, plant overrides, tune overrides, expected cause or None)]}."""
    f = {}
    f["stiction+Stribeck x8"] = [
        (f"Fc x8, static x{st:g}, vs {vs:g}, seed {seed}",
         _plant(coulomb=8 * FC0, static=8 * st * FC0, stribeck_velocity=vs, noise_std=1e-3, seed=seed),
         {"search": {"k_fc_max": 2.0}}, None)
        for st, vs in ((1.5, 0.2), (2.0, 0.05)) for seed in (1, 2)]
    f["coarse encoder"] = [
        (f"{n} counts, noise {ns:g}, seed {seed}", _plant(counts_per_rev=n, noise_std=ns, seed=seed), {}, None)
        for n, ns in ((128, 1e-3), (256, 2e-3), (512, 2e-3)) for seed in (1, 2)]
    f["asymmetry"] = [
        (f"asymmetry {a:g}, seed {seed}",
         _plant(coulomb_asymmetry=a, static=(1 + a) * FC0, noise_std=2e-3, seed=seed), {}, None)
        for a in (0.15, 0.3, 0.4) for seed in (1, 2)]
    f["stiff shaft + load damping"] = [
        (f"k {k:g}, load viscous {lv:g}, seed {seed}", _plant(k=k, load_viscous=lv, noise_std=1e-3, seed=seed),
         {}, None)
        for k, lv in ((5.0, 2e-3), (20.0, 5e-3), (50.0, 1e-2)) for seed in (1, 2)]
    f["heavy motor inertia"] = [
        (f"j1 x{m:g}, seed {seed}", _plant(j1=1e-4 * m, noise_std=1e-3, seed=seed), {}, None)
        for m in (10, 30) for seed in (1, 2)]
    f["u_max near/below Coulomb"] = [
        ("Fc 0.46 V, u_max 0.6 V", _plant(coulomb=4 * FC0, static=4 * FC0, u_max=0.6),
         {"search": {"k_fc_max": 0.55}}, "saturation"),
        ("Fc 0.46 V, u_max 0.4 V", _plant(coulomb=4 * FC0, static=4 * FC0, u_max=0.4),
         {"search": {"k_fc_max": 0.35}}, "no motion"),
        ("Fc 0.23 V, u_max 0.25 V", _plant(coulomb=2 * FC0, static=2 * FC0, u_max=0.25),
         {"search": {"k_fc_max": 0.2}}, "any"),
    ]
    f["tiny friction x0.05"] = [
        (f"Fc x{m:g}, seed {seed}", _plant(coulomb=m * FC0, static=m * FC0, noise_std=1e-4, seed=seed),
         {"search": {"k_fc_max": 0.3, "max_experiments": 16}}, None)
        for m in (0.05, 0.1) for seed in (1, 2)]
    f["demo plant + noise"] = [
        (f"demo, noise {ns:g}, seed {seed}", {"plant": {"viscous": 2e-3}, "sensor": {"noise_std": ns, "seed": seed}},
         {}, None)
        for ns in (2e-3, 1e-2) for seed in (1, 2, 3)]
    # issue 32: the loop's own lag (the PD slow for the sine), a sine the loop cannot follow,
    # the drive's smoothed sign, the friction changing during the tune
    f["slow loop"] = [
        (f"kp {kp:g}, noise 1e-3", {"controller": {"kp": kp}, "sensor": {"noise_std": 1e-3, "seed": 1}}, {},
         (None, "loop lag"))
        for kp in (0.5, 0.35, 0.25, 0.15)] + [
        ("j2 x5, kp 0.5", {"plant": {"j2": 1e-3}, "controller": {"kp": 0.5}}, {}, (None, "loop lag"))]
    f["fast sine"] = [
        (f"sine {fz:g} Hz", {}, {"frequency_hz": fz}, (None, "loop lag")) for fz in (1.25, 1.875, 2.5)]
    f["smoothed sign"] = [
        (f"fc_smooth {w:g}", {"controller": {"fc_smooth": w}}, {}, (None, "smoothed sign"))
        for w in (0.05, 0.2, 0.5, 1.0)]
    f["drift inside a tune"] = [
        ("ramp +30 % over 0..40 s", {"drift": {"coulomb_ramp": 0.3, "coulomb_ramp_start_s": 0.0,
                                                "coulomb_ramp_end_s": 40.0}}, {}, (None, "non-stationary")),
        ("step +30 % at 25 s", {"drift": {"coulomb_step": 0.3, "coulomb_step_time_s": 25.0}}, {},
         (None, "non-stationary")),
        ("step -20 % at 30 s", {"drift": {"coulomb_step": -0.2, "coulomb_step_time_s": 30.0}}, {},
         (None, "non-stationary")),
        ("step +15 % at 34 s", {"drift": {"coulomb_step": 0.15, "coulomb_step_time_s": 34.0}}, {},
         (None, "non-stationary")),
    ]
    # friction x (1 + e sin th): around th = 0 the sine's path averages it to the nominal
    # level (its odd part); the even part e Fc sin(th) sgn(w) adds even harmonics only
    f["position friction"] = [
        (f"coulomb_position {e:g}", {"plant": {"coulomb_position": e, "static": (1 + e) * FC0 * 1.001}}, {}, None)
        for e in (0.2, 0.4)]
    return f


def hidden_families():
    """Issue 32's families again, on values none of families() has (`--hidden`): a reviewer's
    matrix, kept apart so that the strategy is not fitted to it. Loops slowed by kp and kd at
    0.3125 .. 3.75 Hz (lag 0 .. 15 deg and beyond), the smoothed sign at fixed and auto
    amplitudes, friction steps / ramps / exponentials at other times of the tune, sensor noise
    with fixed amplitudes, Stribeck curves, position friction, a two-mass (anti-)resonance near
    the tuning frequency (k 0.001 .. 0.05 N m/rad: the motor's anti-resonance sqrt(k / j2) at
    0.36 .. 2.5 Hz), other Coulomb levels and amplitudes; two or more noise seeds."""
    f = {}
    slow = ((0.7, 0.05, 0.625, 4096, 2e-3, 4), (0.4, 0.03, 0.625, 4096, 1e-3, 5),
            (0.3, 0.05, 0.9375, 8192, 0.0, 1), (0.2, 0.02, 0.625, 4096, 2e-3, 6),
            (0.1, 0.05, 0.625, 4096, 1e-3, 7), (0.06, 0.05, 0.3125, 8192, 0.0, 1),
            (1.0, 0.05, 1.875, 4096, 1e-3, 8), (2.0, 0.02, 3.125, 4096, 0.0, 1),
            (2.0, 0.05, 3.75, 4096, 2e-3, 9), (0.45, 0.01, 1.25, 4096, 1e-3, 10),
            (0.35, 0.05, 0.625, 4096, 2e-3, 1), (0.35, 0.05, 0.625, 4096, 2e-3, 2),
            (0.3, 0.05, 0.625, 4096, 2e-3, 1), (0.3, 0.05, 0.625, 4096, 2e-3, 2),
            (0.25, 0.05, 0.625, 4096, 1e-3, 3), (0.5, 0.005, 0.625, 4096, 1e-3, 1),
            (0.8, 0.003, 1.25, 4096, 1e-3, 2), (3.0, 0.2, 2.5, 4096, 1e-3, 3),
            (0.15, 0.15, 0.625, 4096, 0.0, 1), (0.03, 0.01, 0.3125, 8192, 0.0, 1))
    f["slow loop x frequency"] = [
        (f"kp {kp:g} kd {kd:g} at {fz:g} Hz, noise {ns:g} s{sd}",
         {"controller": {"kp": kp, "kd": kd}, "sensor": {"noise_std": ns, "seed": sd}},
         {"frequency_hz": fz, "period_samples": n}, (None, "loop lag"))
        for kp, kd, fz, n, ns, sd in slow]
    f["smoothed sign x amplitude"] = [
        (f"fc_smooth {w:g} at {a} rad, noise {ns:g}",
         {"controller": {"fc_smooth": w}, "sensor": {"noise_std": ns, "seed": sd}},
         {} if a == "auto" else {"amplitude_rad": a}, (None, "smoothed sign"))
        for w, a, ns, sd in ((0.02, 0.5, 0, 1), (0.1, 2.0, 0, 1), (0.3, 1.0, 0, 1), (0.3, 4.0, 0, 1),
                             (0.7, 2.0, 0, 1), (2.0, 4.0, 0, 1), (0.15, 0.5, 0, 1), (0.5, "auto", 1e-3, 1),
                             (1.5, 1.0, 1e-3, 2), (0.4, 0.5, 1e-3, 3), (0.8, 0.5, 1e-3, 4), (3.0, 2.0, 1e-3, 5))]
    drift = (
        ("step +25 % at 8 s", {"coulomb_step": 0.25, "coulomb_step_time_s": 8.0}, 0.0, 1, {}),
        ("step -30 % at 15 s", {"coulomb_step": -0.3, "coulomb_step_time_s": 15.0}, 1e-3, 2, {}),
        ("step +40 % at 45 s", {"coulomb_step": 0.4, "coulomb_step_time_s": 45.0}, 0.0, 1, {}),
        ("step +10 % at 20 s", {"coulomb_step": 0.1, "coulomb_step_time_s": 20.0}, 1e-3, 3, {}),
        ("step -15 % at 40 s", {"coulomb_step": -0.15, "coulomb_step_time_s": 40.0}, 0.0, 1, {}),
        ("step +30 % at 27 s, s1", {"coulomb_step": 0.3, "coulomb_step_time_s": 27.0}, 2e-3, 1, {}),
        ("step +30 % at 27 s, s2", {"coulomb_step": 0.3, "coulomb_step_time_s": 27.0}, 2e-3, 2, {}),
        ("step -25 % at 33 s", {"coulomb_step": -0.25, "coulomb_step_time_s": 33.0}, 1e-3, 3, {}),
        ("step +20 % at 3 s", {"coulomb_step": 0.2, "coulomb_step_time_s": 3.0}, 0.0, 1, {}),
        ("step -40 % at 22 s", {"coulomb_step": -0.4, "coulomb_step_time_s": 22.0}, 0.0, 1, {}),
        ("step +15 % at 12 s, 1 rad", {"coulomb_step": 0.15, "coulomb_step_time_s": 12.0}, 0.0, 1,
         {"amplitude_rad": 1.0}),
        ("ramp -30 % over 0..60 s", {"coulomb_ramp": -0.3, "coulomb_ramp_start_s": 0.0,
                                    "coulomb_ramp_end_s": 60.0}, 0.0, 1, {}),
        ("ramp +20 % over 10..30 s", {"coulomb_ramp": 0.2, "coulomb_ramp_start_s": 10.0,
                                     "coulomb_ramp_end_s": 30.0}, 1e-3, 4, {}),
        ("ramp -20 % over 20..50 s", {"coulomb_ramp": -0.2, "coulomb_ramp_start_s": 20.0,
                                     "coulomb_ramp_end_s": 50.0}, 0.0, 1, {}),
        ("ramp +50 % over 0..100 s", {"coulomb_ramp": 0.5, "coulomb_ramp_start_s": 0.0,
                                     "coulomb_ramp_end_s": 100.0}, 1e-3, 5, {}),
        ("exp +30 % tau 20 s", {"coulomb_exp": 0.3, "coulomb_exp_start_s": 0.0,
                                "coulomb_exp_tau_s": 20.0}, 0.0, 1, {}),
        ("exp -25 % tau 40 s from 5 s", {"coulomb_exp": -0.25, "coulomb_exp_start_s": 5.0,
                                         "coulomb_exp_tau_s": 40.0}, 1e-3, 5, {}),
        ("exp +50 % tau 8 s from 10 s", {"coulomb_exp": 0.5, "coulomb_exp_start_s": 10.0,
                                         "coulomb_exp_tau_s": 8.0}, 0.0, 1, {}),
        ("exp -40 % tau 15 s", {"coulomb_exp": -0.4, "coulomb_exp_start_s": 0.0, "coulomb_exp_tau_s": 15.0},
         1e-3, 4, {}),
        ("exp +20 % tau 60 s", {"coulomb_exp": 0.2, "coulomb_exp_start_s": 0.0,
                                "coulomb_exp_tau_s": 60.0}, 0.0, 1, {}))
    f["drift inside a tune (hidden)"] = [
        (name, {"drift": d, "sensor": {"noise_std": ns, "seed": sd}}, tn, (None, "non-stationary"))
        for name, d, ns, sd, tn in drift]
    f["sensor noise"] = [
        (f"noise {ns:g}, amplitude {a}, seed {sd}", {"sensor": {"noise_std": ns, "seed": sd}},
         {} if a == "auto" else {"amplitude_rad": a}, (None, "noise"))
        for ns, a, sd in ((3e-3, "auto", 11), (5e-3, "auto", 12), (5e-3, 0.5, 13), (2e-2, "auto", 14),
                          (8e-3, 1.0, 15), (1.5e-2, 0.5, 16), (1e-2, "auto", 2), (1e-2, "auto", 3),
                          (3e-2, "auto", 4), (6e-3, 0.25, 5))]
    f["Stribeck"] = [
        (f"static x{st:g}, vs {vs:g}, noise {ns:g} s{sd}",
         _plant(static=st * FC0, stribeck_velocity=vs, noise_std=ns, seed=sd), {},
         (None, "stick-slip", "amplitude dependence"))
        for st, vs, ns, sd in ((1.3, 0.02, 1e-3, 21), (2.5, 0.1, 1e-3, 22), (3.0, 0.5, 1e-3, 23),
                               (1.8, 1.0, 1e-3, 24), (4.0, 0.01, 1e-3, 25), (2.0, 0.05, 2e-3, 1),
                               (2.0, 0.05, 2e-3, 2), (1.5, 0.3, 2e-3, 3))]
    f["position friction (hidden)"] = [
        (f"coulomb_position {e:g} at {a} rad, noise {ns:g}",
         {"plant": {"coulomb_position": e, "static": (1 + e) * FC0 * 1.001},
          "sensor": {"noise_std": ns, "seed": sd}},
         {} if a == "auto" else {"amplitude_rad": a}, (None, "amplitude dependence"))
        for e, a, ns, sd in ((0.1, "auto", 0, 1), (0.3, 0.5, 0, 1), (0.6, "auto", 0, 1), (0.5, 2.0, 0, 1),
                             (0.8, "auto", 1e-3, 1), (0.4, 1.0, 1e-3, 2), (0.6, 0.5, 1e-3, 3))]
    f["two-mass resonance"] = [
        (f"k {k:g} load viscous {lv:g} at {fz:g} Hz, s{sd}",
         {"plant": {"k": k, "load_viscous": lv}, "sensor": {"noise_std": 1e-3, "seed": sd}},
         {"frequency_hz": fz, "period_samples": n}, (None, "loop lag", "unsettled"))
        for k, lv, fz, n, sd in ((0.002, 0, 0.625, 4096, 31), (0.004, 0, 0.625, 4096, 31),
                                 (0.01, 0, 1.25, 4096, 31), (0.02, 0, 1.875, 4096, 31), (0.05, 0, 2.5, 4096, 31),
                                 (0.003, 0, 0.9375, 8192, 31), (0.001, 0, 0.625, 4096, 32),
                                 (0.0015, 0, 0.625, 4096, 32), (0.006, 0, 0.625, 4096, 32),
                                 (0.001, 2e-4, 0.625, 4096, 32), (0.0033, 0, 0.625, 4096, 32))]
    f["Coulomb levels x amplitudes"] = [
        (f"Fc x{m:g} at {a} rad, s{sd}", _plant(coulomb=m * FC0, static=m * FC0, noise_std=1e-3, seed=sd),
         dict({"search": {"k_fc_max": round(max(0.3, 2.5 * m * 0.1157), 3)}},
              **({} if a == "auto" else {"amplitude_rad": a})), None)
        for m, a, sd in ((0.3, 0.3, 41), (0.5, "auto", 41), (2.0, 1.0, 41), (3.5, "auto", 41), (6.0, 3.0, 41),
                         (0.2, "auto", 41), (10, "auto", 42), (0.1, 1.0, 42), (1.5, 0.25, 42), (8, 0.5, 42))]
    return f


FAST = ("Fc x8, static x2, vs 0.05, seed 1", "256 counts, noise 0.002, seed 1",
        "asymmetry 0.4, seed 1", "k 20, load viscous 0.005, seed 1",
        "Fc 0.46 V, u_max 0.6 V", "Fc 0.46 V, u_max 0.4 V", "demo, noise 0.002, seed 1",
        "kp 0.15, noise 1e-3", "sine 2.5 Hz", "fc_smooth 1", "step -20 % at 30 s")


def judge(t, expected_cause=None):
    """(ok, error re truth or None, covered or None). ``expected_cause``: None (converged or
    any named cause), "any", one cause (the row must stop with it), or a tuple of what is
    right: None in it for converged (within max(2 %, 2 sigma_total) of the truth at the
    tune's end), the causes an unconverged row may name (also those of a first try at a
    higher frequency)."""
    s = t["search"]
    allowed = expected_cause if isinstance(expected_cause, tuple) else None
    if not s["converged"]:
        if allowed is not None:
            return s.get("cause") in allowed, None, None
        if expected_cause in (None, "any"):
            return bool(s["stop_reason"]) and bool(s.get("cause")), None, None
        return s.get("cause") == expected_cause and expected_cause in s["stop_reason"], None, None
    if allowed is not None and None not in allowed:
        return False, None, None
    if allowed is None and expected_cause not in (None, "any"):
        return False, None, None
    err = t["k_fc_star"] / t["true_coulomb_v"] - 1
    covered = abs(t["k_fc_star"] - t["true_coulomb_v"]) <= 2 * s["sigma_v"]
    return bool(abs(err) <= 0.02 or covered), err, bool(covered)


def run_row(plant, tune, capture="raw"):
    with tempfile.TemporaryDirectory() as tmp:
        return bench_tune.run_row(plant, dict(tune, capture=capture), tmp)


def run(fast=False, capture="raw", verbose=True, hidden=False):
    bad, conv, cov, within, counts = [], 0, 0, 0, []
    fam_lines = []
    for fam, rows in (hidden_families() if hidden else families()).items():
        f_conv = f_cov = f_within = 0
        f_counts = []
        if verbose:
            print(f"-- {fam} (capture {capture}): row, truth V, error, sigma_total, experiments, converged, "
                  "parts / [cause] reason", flush=True)
        for name, plant, tune, cause in rows:
            if fast and name not in FAST:
                continue
            t = run_row(plant, tune, capture)
            s = t["search"]
            ok, err, covered = judge(t, cause)
            counts.append(s["experiments"])
            f_counts.append(s["experiments"])
            if s["converged"]:
                f_conv += 1
                f_cov += covered
                f_within += abs(err) <= 0.02
            if not ok:
                bad.append(name)
            if verbose:
                parts = s.get("sigma_parts_v") or {}
                ptxt = " ".join(f"{k[:3]} {100 * v / t['true_coulomb_v']:.2f}" for k, v in parts.items() if v)
                e = f"{100 * err:+6.2f}%" if err is not None else "   -   "
                sig = f"{100 * s['sigma_v'] / t['true_coulomb_v']:5.2f}%" if s["converged"] else "  -   "
                why = ptxt if s["converged"] else f"[{s.get('cause') or '-'}] {s['stop_reason'][:110]}"
                if t.get("frequency_changes"):
                    why += " (at " + ", ".join(f"{ch['to_hz']:g}" for ch in t["frequency_changes"]) + \
                           f" Hz after {t['frequency_changes'][0]['reason'].split(':')[0][:40]})"
                print(f"  {name:40s} {t['true_coulomb_v']:7.4f} {e} {sig} {s['experiments']:3d} "
                      f"{'yes' if s['converged'] else 'no '} {'' if ok else 'FAIL '}{why}", flush=True)
        n = len(f_counts)
        if n:
            conv += f_conv
            cov += f_cov
            within += f_within
            fam_lines.append(f"  {fam:28s} rows {n:2d}  converged {f_conv:2d}  covered "
                             f"{f_cov:2d}/{f_conv:<2d}  within 2 % {f_within:2d}/{f_conv:<2d}  median "
                             f"experiments {statistics.median(f_counts):g}")
    print(f"-- per family (capture {capture}{', hidden families' if hidden else ''}): coverage = truth within "
          "2 sigma_total of the converged rows")
    for line in fam_lines:
        print(line)
    med = statistics.median(counts)
    print(f"capture {capture}: {len(counts)} rows, {conv} converged; coverage {cov}/{conv} "
          f"({100 * cov / max(conv, 1):.0f} %, goal >= 90 %); within 2 % {within}/{conv} "
          f"({100 * within / max(conv, 1):.0f} %, goal >= 90 %); median experiments {med:g} (goal <= 6); "
          f"rows failing acceptance: {len(bad)} {bad if bad else ''}")
    return {"bad": bad, "converged": conv, "covered": cov, "within": within, "median": med,
            "rows": len(counts)}


def seeds(n=15, noise_rad=2e-3, capture="raw"):
    """Coverage over noise seeds on the demo plant and an asymmetric one (issue 22 saw 3/15
    and 5/15 with the noise-only sigma): (name, hits, converged, n, spread of the error)."""
    out = []
    for name, plant in (("demo plant", {"plant": {"viscous": 2e-3}}),
                        ("asymmetric 0.2", {"plant": {"coulomb_asymmetry": 0.2, "static": 1.2 * FC0}})):
        hits = conv = 0
        errs = []
        for seed in range(1, n + 1):
            t = run_row(dict(plant, sensor={"noise_std": noise_rad, "seed": seed}), {}, capture)
            s = t["search"]
            if s["converged"]:
                conv += 1
                errs.append(t["k_fc_star"] / t["true_coulomb_v"] - 1)
                hits += abs(t["k_fc_star"] - t["true_coulomb_v"]) <= 2 * s["sigma_v"]
        out.append((name, hits, conv, n, statistics.pstdev(errs) if len(errs) > 1 else float("nan")))
    return out


def lag_map(capture="raw"):
    """The criterion's bias against the loop's own lag at the tuning frequency (no frequency
    change: tune_at_frequency), configs/plant_twomass.yaml with kp lowered and the sine
    raised: the lag left at K_fc* after the viscous feed-forward, the error of the search's
    root (before the budget), sigma_total, and what tune reports."""
    import math

    from fftune.host import experiments as ex
    print(f"-- bias against the loop's lag (capture {capture}): kp / frequency, lag left at K_fc*, "
          "error of the search's root (of the reported K_fc*), sigma_total, what tune reports")
    cases = [(f"kp {kp:g}", {"controller": {"kp": kp}}, {}) for kp in
             (2.0, 1.5, 1.0, 0.8, 0.6, 0.5, 0.45, 0.4, 0.35, 0.3, 0.25, 0.2, 0.15)]
    cases += [(f"sine {fz:g} Hz", {}, {"frequency_hz": fz}) for fz in (1.25, 1.875, 2.5)]
    real = ex.tune
    ex.tune = ex.tune_at_frequency            # the map is of one frequency: no halving
    try:
        for name, plant, tune in cases:
            t = run_row(plant, tune, capture)
            s = t["search"]
            lag = s.get("loop_lag_deg")
            k = s.get("k_fc_search_v")
            err = f"{100 * (k / t['true_coulomb_v'] - 1):+7.2f} %" if k else "    -    "
            if s["converged"]:
                err += f" (reported {100 * (t['k_fc_star'] / t['true_coulomb_v'] - 1):+6.2f} %)"
            sig = f"{100 * s['sigma_total_v'] / t['true_coulomb_v']:5.2f} %" if s.get("sigma_total_v") else "   -   "
            lag_s = f"{lag:5.2f}" if lag is not None and math.isfinite(lag) else "  -  "
            if s.get("loop_lag_bound_deg") is not None:      # a bound: the search stopped on it
                lag_s = f">={abs(s['loop_lag_bound_deg']):4.1f}"
            print(f"  {name:12s} lag {lag_s} deg  error {err}  sigma_total {sig}  "
                  f"{'converged' if s['converged'] else 'refused: ' + str(s['cause'])}", flush=True)
    finally:
        ex.tune = real


if __name__ == "__main__":
    captures = [sys.argv[sys.argv.index("--capture") + 1]] if "--capture" in sys.argv else ["raw", "stats"]
    failed = False
    for capture in captures:
        res = run(fast="--fast" in sys.argv, capture=capture, verbose=capture == captures[0],
                  hidden="--hidden" in sys.argv)
        failed |= bool(res["bad"]) or res["median"] > 6
        if "--fast" not in sys.argv and "--hidden" not in sys.argv:
            lag_map(capture)
            for name, hits, conv, n, spread in seeds(capture=capture):
                print(f"capture {capture}: {name}, noise 2e-3 rad, {n} seeds: {conv} converged, truth "
                      f"within 2 sigma_total in {hits}; seed-to-seed spread of the error {100 * spread:.2f} %")
    sys.exit(1 if failed else 0)
