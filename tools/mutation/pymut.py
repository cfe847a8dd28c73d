#!/usr/bin/env python3
"""Mutation testing of the analysis and host packages with cosmic-ray (pinned in
tools/mutation/requirements.txt; `make mutation` installs it into .venv).

For each module a fast, focused test selection runs against every mutant (pytest -x: the
first failing test kills it). cosmic-ray edits the module file in place, so it works on a
scratch copy of the package (build/mutation/py/<module>/pkg, first on PYTHONPATH, which
takes precedence over the editable install): the checkout is never touched, and a run
stopped at any point (time budget, Ctrl-C) leaves nothing mutated behind.

Resumable: the cosmic-ray session (build/mutation/py/<module>/session.sqlite) keeps every
result; a later run continues with the pending mutants. It starts over when the module or
its tests change (a hash of them is kept beside the session).

Usage: pymut.py [--budget SECONDS] [--module NAME ...] [--report-only]
"""
import argparse
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, ModuleReport, Mutant, MutationError, announce, pick_modules, fail, run_and_report  # noqa: E402

WORK = ROOT / "build" / "mutation" / "py"

# module -> the tests that exercise it, fastest and most discriminating first (pytest -x)
MODULES = {
    # the 150-seed Monte Carlo check of the known-reference variances (the slowest test by
    # far) is left out for time; the known-reference var_nl test covers the same lines
    "bla": ("analysis/bla.py", ["tests/test_pins_bla_2.py", "tests/test_pins_bla_3.py",
                                "tests/test_pins_bla_reference.py",
                                "tests/test_analysis_bla_helpers.py",
                                "tests/test_analysis_bla_mimo.py",
                                "tests/test_analysis_bla_mutants.py", "tests/test_analysis_bla.py",
                                "tests/test_analysis_bla_moments.py", "tests/test_analysis_detect.py",
                                "tests/test_analysis_anyones_data.py",
                                "tests/test_analysis_groundtruth.py",
                                "--deselect=tests/test_analysis_bla.py::"
                                "test_known_reference_variances_match_monte_carlo_spread"]),
    "hosidf": ("analysis/hosidf.py", ["tests/test_pins_hosidf_2.py", "tests/test_analysis_hosidf_mutants.py",
                                      "tests/test_analysis_hosidf.py"]),
    "tuning": ("analysis/tuning.py", ["tests/test_pins_tune_2.py", "tests/test_pins_tune_track.py",
                                      "tests/test_tune_honest.py",
                                      "tests/test_analysis_tuning_mutants.py",
                                      "tests/test_analysis_tuning.py"]),
    "multisine": ("analysis/multisine.py", ["tests/test_analysis_multisine.py"]),
    # the paper's verdicts: without the shortened `make paper` run (minutes; its numbers
    # come from the functions the fast tests pin)
    "reproduction": ("analysis/reproduction.py", ["tests/test_pins_paper.py", "tests/test_pins_paper_2.py",
                                                  "tests/test_paper.py",
                                                  "--deselect=tests/test_paper.py::test_short_run_reproduces_the_paper",
                                                  "--deselect=tests/test_paper.py::"
                                                  "test_doc_table_is_generated_from_reproduction_json"]),
    "fleet": ("host/fleet.py", ["tests/test_pins_fleet.py", "tests/test_pins_fleet_2.py",
                                "tests/test_fleet_outputs.py", "tests/test_fleet.py"]),
    # the tracker's estimate, its sigma parts and its update/rollback/stop rules (no
    # drive_sim: tests/test_track_host.py runs the host's loop, seconds a test)
    "track": ("analysis/track.py", ["tests/test_pins_track_2.py", "tests/test_pins_track_3.py",
                                    "tests/test_pins_tune_track.py",
                                    "tests/test_track.py", "tests/test_track_honest.py",
                                    "tests/test_track_model_error.py", "tests/test_track_split.py"]),
    # the tune's strategy: its sigma parts, stops and diagnoses (the drive_sim matrix of
    # tests/test_tune_search.py is left out for time; its rows replay in test_tune_strategy)
    "tune_strategy": ("analysis/tune_strategy.py", ["tests/test_pins_tune_2.py",
                                                    "tests/test_tune_strategy.py",
                                                    "tests/test_tune_honest.py",
                                                    "tests/test_pins_tune_strategy_3.py",
                                                    # every tune kind's results pinned (2 s)
                                                    "tests/test_tune_snapshot.py",
                                                    "tests/test_ffmodel.py"]),
    # the machine's summary, exit status and file checks without a bus first, then the
    # sessions on drive_sim (seconds each: a surviving mutant costs tens of seconds)
    "machine": ("host/machine.py", ["tests/test_pins_machine.py", "tests/test_pins_machine_2.py",
                                    "tests/test_machine.py",
                                    # the machine file's refusals, each message in full
                                    "tests/test_envelope.py::"
                                    "test_machine_file_probe_is_one_line_and_nothing_written"]),
}

# The operators kept: one natural mutation per site, as a reader would write it. cosmic-ray
# also replaces every binary operator by all eleven others (shifts and bit operations on
# floats only raise TypeError) and every comparison by all the others; those add cost, not
# information, and are skipped.
KEEP_OPERATORS = re.compile(
    r"core/(ReplaceBinaryOperator_(Add_Sub|Sub_Add|Mul_Div|Div_Mul|Pow_Mul|FloorDiv_Div|Mod_FloorDiv)"
    r"|ReplaceComparisonOperator_(Lt_LtE|LtE_Lt|Gt_GtE|GtE_Gt|Eq_NotEq|NotEq_Eq|Is_IsNot|IsNot_Is"
    r"|In_NotIn|NotIn_In)"
    r"|ReplaceUnaryOperator_Delete_(USub|Not|Invert)"
    r"|NumberReplacer|AddNot|ReplaceAndWithOr|ReplaceOrWithAnd|ReplaceTrueWithFalse"
    r"|ReplaceFalseWithTrue|ZeroIterationForLoop|RemoveDecorator|ReplaceBreakWithContinue"
    r"|ReplaceContinueWithBreak|ExceptionReplacer)$")


def _venv_bin(name):
    return str(Path(sys.executable).parent / name)


def _digest(paths, base=ROOT):
    h = hashlib.sha256()
    for p in [p for p in paths if not p.startswith("-")]:
        h.update(p.encode())
        h.update((base / p.split("::", 1)[0]).read_bytes())   # (a node id: its file)
    h.update(KEEP_OPERATORS.pattern.encode())
    return h.hexdigest()


def _rerun_survivors(session):
    """Forget the survivors' results (they run again); the killed mutants stay killed. Until
    it has run again, such a mutant still counts as a survivor in the report (its job ids
    are kept in rerun.json beside the session)."""
    import json
    import sqlite3
    rerun = session.parent / "rerun.json"
    con = sqlite3.connect(str(session))
    try:
        with con:
            ids = [r[0] for r in con.execute(
                "SELECT job_id FROM work_results WHERE test_outcome = 'SURVIVED'")]
            con.execute("DELETE FROM work_results WHERE test_outcome = 'SURVIVED'")
    finally:
        con.close()
    old = json.loads(rerun.read_text()) if rerun.exists() else []
    rerun.write_text(json.dumps(sorted(set(old) | set(ids))))
    return len(ids)


def _refresh_scratch(mod_dir):
    """A fresh copy of src/fftune + analysis/ + host/ as the package fftune (undoes any leftover)."""
    pkg = mod_dir / "pkg" / "fftune"
    if pkg.exists():
        shutil.rmtree(pkg)
    shutil.copytree(ROOT / "src" / "fftune", pkg, ignore=shutil.ignore_patterns("__pycache__"))
    for sub in ("analysis", "host"):
        shutil.copytree(ROOT / sub, pkg / sub, ignore=shutil.ignore_patterns("__pycache__"))
    return mod_dir / "pkg"


def _snapshot_tests(mod_dir):
    """A frozen copy of tests/ in a tree that looks like the checkout (build/mutation/py/
    <module>/tree: tests/ copied, the other top-level entries linked), so that tests edited
    while a run goes on (the usual way of working on the survivors) do not change the tests
    the running mutants meet halfway: every mutant of a run meets the tests of its digest."""
    tree = mod_dir / "tree"
    if tree.exists():
        shutil.rmtree(tree)
    tree.mkdir()
    for entry in ROOT.iterdir():
        if entry.name == "tests":
            shutil.copytree(entry, tree / "tests", ignore=shutil.ignore_patterns("__pycache__"))
        elif entry.name not in (".git", "build", ".venv"):
            (tree / entry.name).symlink_to(entry)
    return tree


FORKSERVER = Path(__file__).resolve().parent / "forkserver.py"


def _pytest_args(tests, tree):
    return ["-x", "-q", "-p", "no:cacheprovider", "-W", "ignore", "--timeout=300",
            f"--rootdir={tree}"] + [t if t.startswith("-") else str(tree / t) for t in tests]


def _test_command(tests, tree, socket_path=None, test_map=None):
    """pytest on the selection (in the frozen tree); through the fork server when one is
    given, narrowed by the per-test coverage map when one is given (testmap.py)."""
    if socket_path is None:
        return " ".join([sys.executable, "-m", "pytest"] + _pytest_args(tests, tree))
    narrow = [] if test_map is None else ["--map", str(test_map[0]), "--module", str(test_map[1])]
    return " ".join([sys.executable, str(FORKSERVER), "run", str(socket_path)] + narrow
                    + _pytest_args(tests, tree))


def _write_config(config, target, timeout, tests, tree, sock, test_map=None):
    config.write_text(
        "[cosmic-ray]\n"
        f'module-path = "{target}"\n'
        f"timeout = {timeout:.0f}\n"
        "excluded-modules = []\n"
        f'test-command = "{_test_command(tests, tree, sock, test_map)}"\n\n'
        "[cosmic-ray.distributor]\n"
        'name = "local"\n')


def _start_forkserver(mod_dir, pkg_root):
    sock = mod_dir / "fork.sock"
    # (the baseline has rebuilt any stale binary: each mutant's pytest skips the check)
    proc = subprocess.Popen([sys.executable, str(FORKSERVER), "serve", str(sock)], cwd=ROOT,
                            env=dict(_env(pkg_root), FFTUNE_TEST_NO_REBUILD="1"), stdout=subprocess.PIPE, text=True,
                            start_new_session=True)
    if proc.stdout.readline().strip() != "forkserver: ready":
        proc.kill()
        raise MutationError("mutation: the pytest fork server did not start")
    return proc


def _env(pkg_root):
    env = dict(os.environ)
    env["PYTHONPATH"] = str(pkg_root) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    # the scratch package is no checkout (fftune.host.resources finds no firmware_sim
    # beside it): the host's sessions use the checkout's drive_sim
    drive_sim = ROOT / "firmware_sim" / "build" / "drive_sim"
    if drive_sim.exists():
        env.setdefault("FFTUNE_DRIVE_SIM", str(drive_sim))
    return env


def _prepare(name, force=False):
    """Session for one module: (re)initialised when the module or its tests changed."""
    module, tests = MODULES[name]
    mod_dir = WORK / name
    mod_dir.mkdir(parents=True, exist_ok=True)
    session, stamp, config = mod_dir / "session.sqlite", mod_dir / "digest", mod_dir / "config.toml"
    # code and tests apart: when only the tests changed (tests added), the killed mutants
    # stay killed and the survivors run again; a changed module starts over
    tree = _snapshot_tests(mod_dir)
    digest = _digest([module]) + "\n" + _digest(tests, tree)
    pkg_root = _refresh_scratch(mod_dir)
    target = pkg_root / "fftune" / Path(module).parent.name / Path(module).name
    sock = mod_dir / "fork.sock"
    kept = None if force or not session.exists() or not stamp.exists() else stamp.read_text()
    if kept == digest and (mod_dir / "testmap.json").exists():
        return session, config, pkg_root
    tests_only = kept is not None and kept.split("\n")[0] == digest.split("\n")[0]
    if not tests_only:
        for p in (session, stamp, mod_dir / "rerun.json"):
            p.unlink(missing_ok=True)
    env = _env(pkg_root)
    # baseline: the selection must pass on the unmutated code, its time sets the timeout
    t0 = time.monotonic()
    base = subprocess.run(_test_command(tests, tree).split(), cwd=ROOT, env=env,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    elapsed = time.monotonic() - t0
    if base.returncode != 0:
        tail = base.stdout.strip().splitlines()[-1:] or ["(no output)"]
        raise MutationError(f"mutation: {name}: the tests fail on the unmutated code "
                            f"({' '.join(tests)}): {tail[0]}")
    timeout = max(30.0, 5.0 * elapsed)
    test_map = _build_test_map(name, tests, tree, target, env, mod_dir)
    # (the config holds the test command: a selection that gained or lost files must reach
    # the mutants, not only the edits to the files it had)
    _write_config(config, target, timeout, tests, tree, sock, test_map)
    if tests_only:
        n = _rerun_survivors(session)
        stamp.write_text(digest)
        print(f"mutation: {name}: the tests changed: {n} survivor(s) run again, the killed "
              f"mutants kept (baseline tests {elapsed:.1f} s)", flush=True)
        return session, config, pkg_root
    init = subprocess.run([_venv_bin("cosmic-ray"), "init", str(config), str(session)], cwd=ROOT,
                          env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if init.returncode != 0:
        raise MutationError(f"mutation: {name}: cosmic-ray init failed: "
                            f"{init.stdout.strip().splitlines()[-1:]}")
    _skip_unkept_operators(session)
    stamp.write_text(digest)
    print(f"mutation: {name}: new session, baseline tests {elapsed:.1f} s, timeout {timeout:.0f} s",
          flush=True)
    return session, config, pkg_root


def _build_test_map(name, tests, tree, target, env, mod_dir):
    """The per-test coverage map of the unmutated module (testmap.py): (map file, module
    file) for the fork server's client, which narrows each mutant's run to the tests that
    execute what it changed. One more run of the selection, under coverage.py."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import testmap
    args = [a for a in _pytest_args(tests, tree) if a != "-x"]
    collect = subprocess.run([sys.executable, "-m", "pytest", "--collect-only"] + args,
                             cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True)
    node_ids = [ln.strip() for ln in collect.stdout.splitlines() if "::" in ln and " " not in ln.strip()]
    cov_file = mod_dir / "coverage.data"
    cov_file.unlink(missing_ok=True)
    cov_env = dict(env, COVERAGE_FILE=str(cov_file))
    run = subprocess.run([sys.executable, "-m", "pytest", f"--cov={target.parent}",
                          "--cov-context=test", "--cov-report="] + args,
                         cwd=ROOT, env=cov_env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if collect.returncode != 0 or run.returncode != 0 or not node_ids:
        tail = (run.stdout or collect.stdout).strip().splitlines()[-1:] or ["(no output)"]
        raise MutationError(f"mutation: {name}: the coverage run of the tests failed: {tail[0]}")
    test_map = testmap.build(cov_file, target, node_ids)
    map_path = mod_dir / "testmap.json"
    testmap.save(map_path, target.read_text(encoding="utf-8"), test_map)
    narrowed = sum(1 for v in test_map["lines"].values() if v != testmap.ALL)
    print(f"mutation: {name}: per-test coverage of {len(node_ids)} tests: {narrowed} of "
          f"{len(test_map['lines'])} executed statements run only the tests that reach them",
          flush=True)
    return map_path, target


def _skip_unkept_operators(session):
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    with use_db(str(session), WorkDB.Mode.open) as db:
        skip = [item.job_id for item in db.work_items
                if not all(KEEP_OPERATORS.match(m.operator_name) for m in item.mutations)]
        if skip:
            db.set_multiple_results(skip, WorkResult(worker_outcome=WorkerOutcome.SKIPPED,
                                                     output="operator not in the kept set"))


def _exec(name, session, config, pkg_root, deadline):
    """cosmic-ray exec until done or the deadline (then its process group is stopped)."""
    left = deadline - time.monotonic()
    if left <= 5:
        return False
    server = _start_forkserver(WORK / name, pkg_root)
    proc = subprocess.Popen([_venv_bin("cosmic-ray"), "exec", str(config), str(session)], cwd=ROOT,
                            env=_env(pkg_root), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        _, err = proc.communicate(timeout=left)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
        _refresh_scratch(WORK / name)          # the job in progress may have left its mutation
        return False
    except KeyboardInterrupt:
        os.killpg(proc.pid, signal.SIGKILL)
        _refresh_scratch(WORK / name)
        raise
    finally:
        server.terminate()
        server.wait()
    if proc.returncode != 0:
        raise MutationError(f"mutation: {name}: cosmic-ray exec failed: "
                            f"{(err or '').strip().splitlines()[-1:]}")
    return True


def _diff_lines(diff):
    minus = [ln[1:].strip() for ln in (diff or "").splitlines()
             if ln.startswith("-") and not ln.startswith("---")]
    plus = [ln[1:].strip() for ln in (diff or "").splitlines()
            if ln.startswith("+") and not ln.startswith("+++")]
    return " / ".join(minus), " / ".join(plus)


def report(name):
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    module, _ = MODULES[name]
    rep = ModuleReport(module)
    session = WORK / name / "session.sqlite"
    if not session.exists():
        rep.note = "not run yet"
        return rep
    source = (ROOT / module).read_text(encoding="utf-8").splitlines()
    import json
    rerun_file = WORK / name / "rerun.json"
    rerun = set(json.loads(rerun_file.read_text())) if rerun_file.exists() else set()
    with use_db(str(session), WorkDB.Mode.open) as db:
        results = dict(db.results)
        for item in db.work_items:
            spec = item.mutations[0]
            line = spec.start_pos[0]
            res = results.get(item.job_id)
            if res is not None and res.worker_outcome == WorkerOutcome.SKIPPED:
                continue
            original = source[line - 1].strip() if line <= len(source) else ""
            if res is None and item.job_id in rerun:
                # survived the earlier tests, not run on the present ones yet: a survivor
                outcome, mutated = "survived", "(survived the earlier tests; not run again yet)"
            elif res is None:
                outcome, mutated = "pending", ""
            else:
                o, mutated = _diff_lines(res.diff)
                original = o or original
                if res.worker_outcome in (WorkerOutcome.EXCEPTION, WorkerOutcome.NO_TEST) \
                        or res.test_outcome == TestOutcome.INCOMPETENT:
                    outcome = "not-viable"
                elif res.test_outcome == TestOutcome.SURVIVED:
                    outcome = "survived"
                else:
                    outcome = "killed"
            rep.mutants.append(Mutant(Path(module).name, line, spec.operator_name.split("/")[-1],
                                      original, mutated, outcome))
    return rep


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modules", metavar="LIST",
                    help="only these modules (space or comma separated, as MUTATION_MODULES; "
                         "the other driver's names are skipped); default: all")
    ap.add_argument("--module", action="append", default=[], help="one module (repeatable)")
    ap.add_argument("--budget", type=float, default=float(os.environ.get("MUTATION_BUDGET", 3600)),
                    help="seconds for this run, all modules together (default 3600; "
                         "pending mutants are run by the next call)")
    ap.add_argument("--report-only", action="store_true", help="print the scores, run nothing")
    ap.add_argument("--restart", action="store_true", help="discard the sessions, start over")
    args = ap.parse_args(argv)
    spec = " ".join(args.module + ([args.modules] if args.modules else [])) or None
    try:
        names = pick_modules(spec, MODULES)
    except MutationError as exc:
        fail(str(exc))
    if not names:
        return 0                      # MUTATION_MODULES names only the other driver's modules
    # a stop by SIGTERM (or SIGINT, ignored in background jobs) cleans up like Ctrl-C
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        import cosmic_ray  # noqa: F401
    except ImportError:
        fail("mutation: cosmic-ray is not installed in this Python "
             f"({sys.executable}): pip install -r tools/mutation/requirements.txt")
    def run():
        deadline = time.monotonic() + args.budget
        for name in names:
            session, config, pkg_root = _prepare(name, force=args.restart)
            announce(name, deadline)
            _exec(name, session, config, pkg_root, deadline)
    return run_and_report(None if args.report_only else run, names, report)

if __name__ == "__main__":
    sys.exit(main())
