"""The whole friction feed-forward at once (issue 35): `tune.method: model`
(fftune.analysis.ffmodel) against the root search (`search`), on the firmware core + plant
through ctypes (tests/fwsim_drive.py: the same C controller, feed-forward terms and plant as
drive_sim, no CANopen).

Part 1, per set-up and method: closed-loop experiments and excitation seconds to a result,
each term against the plant's truth (value, sigma, error, in sigmas), the odd and even
levels at the verifying experiment, and the rms tracking error at the set-up's tune
amplitude with no feed-forward, with the search's K_fc* + K_v* and with the model's terms.
Set-ups: the demo plant (configs/plant_twomass.yaml, viscous 2e-3), the paper set-up
(configs/plant_paper.yaml: run-out, the paper's even 3 %), an asymmetric plant (0.3), a
stiff shaft with load-side damping and strong stiction with a Stribeck curve.

Part 2: K_fc alone with the model method over the tune matrix's families
(tests/bench/bench_tune_matrix.py): per row the error, sigma, experiments; per family the
median; then the acceptance.

`--fast`: part 1 only for the demo and the paper set-up.
"""
import math
import os
import statistics
import sys
import tempfile

import numpy as np
import yaml

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir))
sys.path.insert(0, os.path.join(REPO, "tests"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import bench_tune  # noqa: E402
import bench_tune_matrix  # noqa: E402
from fftune.host import experiments as ex  # noqa: E402

FC0 = bench_tune.FC0


def truth_of(plant_path):
    with open(plant_path) as fh:
        p = yaml.safe_load(fh)["plant"]
    km = p["km"]
    return {"coulomb": p["coulomb"] / km, "asymmetry": p["coulomb"] * p.get("coulomb_asymmetry", 0.0) / km,
            "viscous": (p["viscous"] + p.get("load_viscous", 0.0)) / km,
            "position": p["coulomb"] * p.get("coulomb_position", 0.0) / km}


def _config(plant_path, tune_over, capture="raw"):
    model = tune_over.get("model", {})
    cfg = bench_tune.tune_config({k: v for k, v in dict(tune_over, capture=capture).items() if k != "model"})
    cfg["tune"]["model"].update(model)
    with open(plant_path) as fh:
        ctl = yaml.safe_load(fh)["controller"]
    cfg["drive"]["controller"].update({k: ctl[k] for k in ("kp", "kd", "tau_d", "u_max")})
    if capture == "stats":
        with open(plant_path) as fh:
            counts = yaml.safe_load(fh)["sensor"]["counts_per_rev"]
        cfg["detect"]["encoder_step_rad"] = 2 * math.pi / counts if counts else 1e-9
    return cfg


def excitation_s(cfg, experiments):
    t = cfg["tune"]
    return experiments * (t["settle_periods"] + t["periods"]) * t["period_samples"] / 2560.0


def tune_once(plant_path, tune_over, workdir, capture="raw"):
    from fwsim_drive import FwSimDrive
    drive = FwSimDrive(plant_path)
    try:
        drive.enable()
        cfg = _config(plant_path, tune_over, capture)
        session = ex.Session(drive, cfg, os.path.join(workdir, "out"), log=lambda s: None)
        results, _ = ex.tune(session)
        return results, cfg
    finally:
        drive.close()


def rms_error(plant_path, amplitude, gains, tune_cfg):
    """rms tracking error of one sine experiment at ``amplitude`` with ``gains``."""
    from fwsim_drive import FwSimDrive
    drive = FwSimDrive(plant_path)
    try:
        drive.enable()
        t = tune_cfg["tune"]
        n = t["period_samples"]
        req = {"exc_kind": 1, "exc_inject": 0, "exc_amplitude": amplitude, "exc_offset": 0.0, "exc_period": n,
               "exc_sine_cycles": int(round(t["frequency_hz"] * n / 2560.0)),
               "exc_settle_periods": t["settle_periods"], "exc_record_periods": t["periods"],
               "kfc": 0.0, "kv": 0.0, "kfa": 0.0, "kps": 0.0, "kpc": 0.0}
        req.update(gains)
        rec = drive.run(req, signals=("error",))
        return float(np.sqrt(np.mean(rec.signals["error"] ** 2)))
    finally:
        drive.close()


SETUPS = {
    "demo plant": ("plant_twomass.yaml", {"plant": {"viscous": 2e-3}}, ["coulomb", "viscous"], {}),
    "paper set-up": ("plant_paper.yaml", {}, ["coulomb", "viscous", "position"],
                     {"amplitude_rad": 0.125, "periods": 4}),
    "asymmetric 0.3": ("plant_twomass.yaml", {"plant": {"coulomb_asymmetry": 0.3, "static": 1.31 * FC0,
                                                        "viscous": 2e-3}},
                       ["coulomb", "asymmetry", "viscous"], {}),
    "stiff shaft + load damping": ("plant_twomass.yaml", {"plant": {"k": 20.0, "load_viscous": 5e-3},
                                                          "sensor": {"noise_std": 1e-3, "seed": 1}},
                                   ["coulomb", "viscous"], {}),
    "stiction + Stribeck x8": ("plant_twomass.yaml", {"plant": {"coulomb": 8 * FC0, "static": 12 * FC0,
                                                                "stribeck_velocity": 0.2},
                                                      "sensor": {"noise_std": 1e-3, "seed": 1}},
                               ["coulomb", "viscous"], {"search": {"k_fc_max": 2.0}}),
}
FAST = ("demo plant", "paper set-up")


def part1(fast=False):
    from fwsim_drive import plant_file
    bad = []
    print("Part 1: per set-up, the root search (K_fc, then K_v) and the model method (every term at once)")
    for name, (base, over, terms, tune_over) in SETUPS.items():
        if fast and name not in FAST:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            plant = plant_file(over, base=os.path.join(REPO, "configs", base), directory=tmp)
            truth = truth_of(plant)
            search_over = dict(tune_over, viscous={"enabled": True, "k_v_max": 0.3, "max_experiments": 8})
            rs, cfg_s = tune_once(plant, search_over, tmp)
            rm, cfg_m = tune_once(plant, dict(tune_over, method="model", terms=terms), tmp)
            amp = tune_over.get("amplitude_rad", rs["amplitude_rad"])
            if amp == "auto":
                amp = rs["amplitude_rad"]
            kfc = rs["k_fc_star"] or 0.0
            kv = (rs["viscous"] or {}).get("k_v_star") or 0.0
            n_kv = (rs["viscous"] or {}).get("experiments", 0) + (1 if rs["viscous"] else 0)
            rms0 = rms_error(plant, amp, {}, cfg_s)
            rms_s = rms_error(plant, amp, {"kfc": kfc, "kv": kv}, cfg_s)
            g = rm["model"]["gains"] or {}
            rms_m = rms_error(plant, amp, g, cfg_m)
        n_s = rs["search"]["experiments"] + n_kv
        print(f"-- {name} (truth: " + ", ".join(f"{k} {v:.4g}" for k, v in truth.items() if v) + ")")
        print(f"   search: K_fc* {kfc:.5f} V ({100 * (kfc / truth['coulomb'] - 1):+.2f} %), K_v* {kv:.4g} V s/rad; "
              f"{n_s} experiments ({rs['search']['experiments']} + {n_kv} for K_v), "
              f"{excitation_s(cfg_s, n_s):.0f} s of excitation; odd at K_fc* {100 * (rs['ratio_at_k_fc_star'] or 0):.2f} %")
        m = rm["model"]
        print(f"   model:  {rm['experiments']} experiments, {excitation_s(cfg_m, rm['experiments']):.0f} s; "
              f"{'converged' if m['converged'] else 'NOT converged: ' + str(m['stop_reason'])}; "
              f"odd {100 * (rm['odd_ratio_at_optimum'] or 0):.2f} %, even {100 * (rm['even_ratio_at_optimum'] or 0):.2f} % "
              f"at {m['verification']['amplitude_rad'] if m['verification'] else float('nan'):.3g} rad")
        ok_terms = True
        for term, t in rm["terms"].items():
            tr = truth[term]
            err = (t["value"] / tr - 1) if tr else float("nan")
            nsig = (t["value"] - tr) / t["sigma"] if t["sigma"] else float("inf")
            covered = abs(t["value"] - tr) <= 2 * t["sigma"]
            ok_terms &= covered or abs(err) <= 0.02
            extra = ""
            if term == "coulomb" and "fc_plus_v" in t:
                fp, fm_ = truth["coulomb"] + truth["asymmetry"], truth["coulomb"] - truth["asymmetry"]
                extra = (f"; Fc+ {t['fc_plus_v']:.5f} ({100 * (t['fc_plus_v'] / fp - 1):+.2f} %), "
                         f"Fc- {t['fc_minus_v']:.5f} ({100 * (t['fc_minus_v'] / fm_ - 1):+.2f} %)")
            print(f"     {term:10s} {t['value']:.5f} +- {t['sigma']:.5f} {t['unit']:8s} truth {tr:.5f}: "
                  f"{100 * err:+.2f} % ({nsig:+.1f} sigma){extra}")
        print(f"   rms tracking error at {amp:.3g} rad: none {rms0:.3g} rad, K_fc*+K_v* {rms_s:.3g} rad, "
              f"model terms {rms_m:.3g} rad")
        if name == "paper set-up":
            checks = {"even <= 0.5 %": (rm["even_ratio_at_optimum"] or 1) <= 0.005,
                      "odd <= 0.5 %": (rm["odd_ratio_at_optimum"] or 1) <= 0.005,
                      "each term within 2 sigma": all(abs(t["value"] - truth[k]) <= 2 * t["sigma"]
                                                      for k, t in rm["terms"].items()),
                      "<= 5 experiments": rm["experiments"] <= 5,
                      "rms below K_fc*+K_v*": rms_m < rms_s}
            print("   acceptance (paper set-up): " + ", ".join(f"{k}: {'ok' if v else 'FAIL'}" for k, v in checks.items()))
            bad += [f"paper: {k}" for k, v in checks.items() if not v]
        if name.startswith("asymmetric"):
            t = rm["terms"]["coulomb"]
            fp, fm_ = truth["coulomb"] + truth["asymmetry"], truth["coulomb"] - truth["asymmetry"]
            ok = all(abs(e / tr - 1) <= 0.02 or abs(e - tr) <= 2 * t["fc_plus_minus_sigma_v"]
                     for e, tr in ((t["fc_plus_v"], fp), (t["fc_minus_v"], fm_)))
            print(f"   acceptance (asymmetric): Fc+ and Fc- within 2 % or 2 sigma: {'ok' if ok else 'FAIL'}")
            if not ok:
                bad.append("asymmetric: Fc+/Fc-")
        if not ok_terms and m["converged"]:
            bad.append(f"{name}: a term off by more than max(2 %, 2 sigma)")
    return bad


def part2(capture="raw"):
    from fwsim_drive import plant_file
    print(f"Part 2: K_fc alone, method model, over the tune matrix's families (capture {capture})")
    print(f"{'row':44s} {'true Fc':>8s} {'K_fc*':>8s} {'error':>8s} {'sigma':>7s} {'exp':>4s}  result")
    fam_medians, wrong, within_rows = [], [], []
    for fam, rows in bench_tune_matrix.families().items():
        errs, sigs, counts = [], [], []
        for name, plant_over, tune_over, cause in rows:
            with tempfile.TemporaryDirectory() as tmp:
                plant = plant_file(plant_over, base=bench_tune_matrix.bench_tune.REPO + "/configs/plant_twomass.yaml",
                                   directory=tmp)
                truth = truth_of(plant)["coulomb"]
                r, _ = tune_once(plant, dict(tune_over, method="model", terms=["coulomb"]), tmp, capture)
            m = r["model"]
            counts.append(r["experiments"])
            if m["converged"]:
                c = r["terms"]["coulomb"]
                err = c["value"] / truth - 1
                errs.append(abs(err))
                sigs.append(c["sigma"] / c["value"])
                ok = abs(err) <= 0.01 and c["sigma"] <= 0.01 * c["value"]
                within_rows.append(ok)
                confidently_wrong = abs(err) > max(0.02, 2 * c["sigma"] / truth) or cause not in (None, "any")
                if confidently_wrong:
                    wrong.append(name)
                print(f"{name:44s} {truth:8.5f} {c['value']:8.5f} {100 * err:+7.2f}% {100 * c['sigma'] / c['value']:6.2f}% "
                      f"{r['experiments']:4d}  {'within 1 %, sigma <= 1 %' if ok else ''}"
                      f"{' CONFIDENTLY WRONG' if confidently_wrong else ''}")
            else:
                exp_ok = cause is not None
                print(f"{name:44s} {truth:8.5f} {'-':>8s} {'-':>8s} {'-':>7s} {r['experiments']:4d}  "
                      f"not converged ({'expected' if exp_ok else 'the reason named'}): {m['stop_reason']}")
                if cause is None:
                    within_rows.append(False)
        if errs:
            fam_medians.append((fam, statistics.median(errs), statistics.median(sigs), statistics.median(counts)))
            print(f"   family {fam}: median |error| {100 * fam_medians[-1][1]:.2f} %, median sigma "
                  f"{100 * fam_medians[-1][2]:.2f} %, median experiments {fam_medians[-1][3]:g}")
    med_err = statistics.median(f[1] for f in fam_medians)
    med_sig = statistics.median(f[2] for f in fam_medians)
    med_n = statistics.median(f[3] for f in fam_medians)
    print(f"acceptance (K_fc alone, median over {len(fam_medians)} families): |error| {100 * med_err:.2f} % "
          f"(<= 1 %), sigma {100 * med_sig:.2f} % (<= 1 %), experiments {med_n:g} (<= 3); rows within 1 % with "
          f"sigma <= 1 %: {sum(within_rows)} / {len(within_rows)}; confidently wrong: {len(wrong)} {wrong}")
    bad = []
    if not (med_err <= 0.01 and med_sig <= 0.01 and med_n <= 3):
        bad.append("K_fc alone medians")
    bad += [f"confidently wrong: {w}" for w in wrong]
    return bad


def main(argv):
    fast = "--fast" in argv
    bad = part1(fast=fast)
    if not fast:
        bad += part2("stats" if "--stats" in argv else "raw")
    print("bench_ffmodel: " + ("all acceptance checks passed" if not bad else "FAILED: " + "; ".join(bad)))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
