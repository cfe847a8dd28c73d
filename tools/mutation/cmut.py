#!/usr/bin/env python3
"""Mutation testing of firmware_sim's C code with a small harness of our own.

Each mutant is ONE textual change of one source line (the operators below), applied to a
scratch copy of firmware_sim (build/mutation/c/work): the mutated file is compiled alone
with the project's flags (-Werror: a mutant the compiler refuses is "not viable", not
counted), linked with the other objects of the unmodified build into the test programs
that cover it, and those run with a time limit. A failing, crashing or hanging test
program kills the mutant.

Operators (one mutation per site and operator; code only: comments, strings, character
constants and preprocessor lines are never touched):
  relational   <  <=  >  >=  ==  !=      ->  <= < >= > != ==
  arithmetic   a + b  a - b  a * b  a / b a % b  (binary, spaced as the code is written)
                                         ->  -  +  /  *  *
  logical      &&  ||                    ->  ||  &&
  negation     !x                        ->  x
  bitwise      a | b  a & b  a ^ b  << >>  ->  &  |  |  >>  <<
  update       +=  -=  ++  --            ->  -=  +=  --  ++
  boolean      true false                ->  false true
  constant     integer literal k         ->  k + 1 (1 -> 0); float literal x -> x + 1

Results are kept per module (build/mutation/c/<module>.json) after every mutant: a run
stopped by its time budget continues where it stopped. A module starts over when its
source or its tests change.

Usage: cmut.py [--budget SECONDS] [--module core/ms.c ...] [--report-only] [--restart]
"""
import argparse
import fcntl
import hashlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, ModuleReport, Mutant, MutationError, announce, fail, pick_modules, run_and_report  # noqa: E402

FW = ROOT / "firmware_sim"
WORK = ROOT / "build" / "mutation" / "c"
TREE = WORK / "work"              # scratch copy: work/firmware_sim, work/configs, work/tests/vectors

# module -> the test programs that cover it
CORE_TESTS = ["test_core", "test_plant"]
MODULES = {
    "core/ctl.c": CORE_TESTS, "core/gen.c": CORE_TESTS, "core/ms.c": CORE_TESTS,
    "core/rec.c": CORE_TESTS, "core/run.c": CORE_TESTS,
    "canopen/co_sdo.c": ["co_test"], "canopen/co_nmt.c": ["co_test"], "canopen/co_pdo.c": ["co_test"],
    "plant/plant.c": ["test_plant"],
    # the task generator is tested from Python through libfwsim.so (tests/test_track.py):
    # a "pytest:" program links the mutant into build/libfwsim.so of the scratch tree and
    # runs that test file there (its copy of tests/ finds the scratch firmware_sim)
    "core/task.c": ["test_core", "pytest:tests/test_pins_task.py tests/test_track.py"],
}
# the files a "pytest:" program reads (part of its module's tests digest)
PYTEST_FILES = {"pytest:tests/test_pins_task.py tests/test_track.py": [
    "tests/test_pins_task.py", "tests/test_track.py", "tests/track_sim.py", "tests/conftest.py",
    "firmware_sim/tests/fwsim.py"]}

# The compile flags of firmware_sim/Makefile and canopen.mk (kept in step with them; the
# baseline build below fails loudly if the unmutated code does not pass these tests).
CSTD_WARN = ["-std=c11", "-Wall", "-Wextra", "-Werror"]
FLAGS = {
    "core": CSTD_WARN + ["-Wdouble-promotion", "-O2", "-Icore", "-Iplant", "-Ibuild/gen"],
    "plant": CSTD_WARN + ["-O2", "-Icore", "-Iplant", "-Ibuild/gen"],
    "tests": CSTD_WARN + ["-O2", "-D_DEFAULT_SOURCE", "-Icore", "-Iplant", "-Ibuild/gen", "-Itests"],
    "canopen": CSTD_WARN + ["-O1", "-DCO_SIM_BUILD", "-Ibuild/co_double", "-Icanopen",
                            "-Icanopen/tests", "-Ibuild/gen"],
}
CC = os.environ.get("CC", "cc")
# part of every module's digest: change it when the operators or the build change, so that
# kept results are not mixed with results of another harness
HARNESS_VERSION = "2"

# --------------------------------------------------------------------------- operators

_TOKEN = re.compile(r"""
    (?P<float>(?<![\w.])(?:\d+\.\d*|\.\d+)(?:[eE][-+]?\d+)?[fF]?(?![\w.]))
  | (?P<int>(?<![\w.])(?:0[xX][0-9A-Fa-f]+|\d+)[uUlL]*(?![\w.]))
  | (?P<word>\b(?:true|false)\b)
  | (?P<op><<=|>>=|<<|>>|->|<=|>=|==|!=|&&|\|\||\+\+|--|\+=|-=|\*=|/=|[-+*/%<>!&|^])
""", re.VERBOSE)

_REL = {"<": "<=", "<=": "<", ">": ">=", ">=": ">", "==": "!=", "!=": "=="}
_ARITH = {"+": "-", "-": "+", "*": "/", "/": "*", "%": "*"}
_BIT = {"|": "&", "&": "|", "^": "|", "<<": ">>", ">>": "<<"}
_UPDATE = {"+=": "-=", "-=": "+=", "++": "--", "--": "++"}


def _code_mask(lines):
    """Per line, the text with comments, strings and char constants blanked (same length);
    preprocessor lines fully blanked."""
    out, in_comment = [], False
    for line in lines:
        chars, i, n = list(line), 0, len(line)
        if not in_comment and line.lstrip().startswith("#"):
            out.append(" " * n)
            continue
        while i < n:
            if in_comment:
                end = line.find("*/", i)
                stop = n if end < 0 else end + 2
                chars[i:stop] = " " * (stop - i)
                in_comment, i = end < 0, stop
                continue
            c = line[i]
            if line.startswith("/*", i):
                in_comment = True
                continue
            if line.startswith("//", i):
                chars[i:] = " " * (n - i)
                break
            if c in "\"'":
                j = i + 1
                while j < n and line[j] != c:
                    j += 2 if line[j] == "\\" else 1
                chars[i:j + 1] = " " * (min(j + 1, n) - i)
                i = j + 1
                continue
            i += 1
        out.append("".join(chars))
    return out


def _is_binary(code, start, end):
    """A binary operator as this code base writes it: a space on both sides."""
    return start > 0 and end < len(code) and code[start - 1] == " " and code[end] == " "


def _bump(literal, kind):
    if kind == "int":
        m = re.match(r"(0[xX][0-9A-Fa-f]+|\d+)([uUlL]*)$", literal)
        digits, suffix = m.groups()
        value = int(digits, 16) if digits[:2].lower() == "0x" else int(digits)
        new = 0 if value == 1 else value + 1
        return (hex(new) if digits[:2].lower() == "0x" else str(new)) + suffix
    m = re.match(r"(.*?)([fF]?)$", literal)
    body, suffix = m.groups()
    return repr(float(body) + 1.0) + suffix


def mutants_of(source):
    """[(line_no, col, operator, mutated_line)] for every mutation site of a C file."""
    lines = source.split("\n")
    masked = _code_mask(lines)
    result = []
    for ln, (line, code) in enumerate(zip(lines, masked), 1):
        for m in _TOKEN.finditer(code):
            kind, tok, s, e = m.lastgroup, m.group(), m.start(), m.end()
            new, op = None, None
            if kind in ("int", "float"):
                new, op = _bump(tok, kind), "constant"
            elif kind == "word":
                new, op = ("false" if tok == "true" else "true"), "boolean"
            elif tok in _REL and (tok not in "<>" or _is_binary(code, s, e)):
                new, op = _REL[tok], "relational"
            elif tok in ("&&", "||"):
                new, op = ("||" if tok == "&&" else "&&"), "logical"
            elif tok in _ARITH and _is_binary(code, s, e):
                new, op = _ARITH[tok], "arithmetic"
            elif tok in _BIT and _is_binary(code, s, e):
                new, op = _BIT[tok], "bitwise"
            elif tok in _UPDATE:
                new, op = _UPDATE[tok], "update"
            elif tok == "!":
                new, op = "", "negation"
            if new is not None:
                result.append((ln, s, op, line[:s] + new + line[e:]))
    return result


# --------------------------------------------------------------------------- build + run

def _run(cmd, cwd, timeout=None):
    return subprocess.run(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True, timeout=timeout)


def _prepare_tree():
    """Scratch copy of firmware_sim (+ the configs and vectors its tests read), built."""
    if TREE.exists():
        shutil.rmtree(TREE)
    TREE.mkdir(parents=True)
    shutil.copytree(FW, TREE / "firmware_sim", ignore=shutil.ignore_patterns("build", "__pycache__"))
    shutil.copytree(ROOT / "configs", TREE / "configs", ignore=shutil.ignore_patterns("__pycache__"))
    # (the vectors the C tests read, and the Python tests of the "pytest:" programs)
    shutil.copytree(ROOT / "tests", TREE / "tests", ignore=shutil.ignore_patterns("__pycache__", "vm"))
    fw = TREE / "firmware_sim"
    res = _run(["make", "--no-print-directory", f"PYTHON={sys.executable}", "gen", "canopen-gen",
                "build/gen/ms_vectors.h", "build/co_double/drv.h"], fw)
    if res.returncode != 0:
        raise MutationError(f"mutation: firmware_sim generation step failed: {res.stdout.strip()[-300:]}")
    objs = WORK / "obj"
    if objs.exists():
        shutil.rmtree(objs)
    objs.mkdir(parents=True)
    for src in sorted(fw.glob("core/*.c")) + sorted(fw.glob("plant/*.c")) + \
            sorted(fw.glob("canopen/co_*.c")) + sorted(fw.glob("canopen/tests/*.c")) + \
            [fw / "build/gen/od_table.c", fw / "tests/test_core.c", fw / "tests/test_plant.c"]:
        rel = src.relative_to(fw).as_posix()
        err = _compile(rel, fw / rel, _obj(rel))
        if not err and rel.startswith(("core/", "plant/")):
            err = _compile(rel, fw / rel, _obj(rel, pic=True), pic=True)
        if err:
            raise MutationError(f"mutation: unmutated {rel} does not compile: {err}")


def _flags_for(rel):
    if rel.startswith("core/"):
        return FLAGS["core"]
    if rel.startswith("plant/"):
        return FLAGS["plant"]
    if rel.startswith("tests/"):
        return FLAGS["tests"]
    return FLAGS["canopen"]


def _obj(rel, pic=False):
    return WORK / "obj" / (rel.replace("/", "__") + (".pic.o" if pic else ".o"))


def _compile(rel, src, obj, pic=False):
    res = _run([CC] + _flags_for(rel) + (["-fPIC"] if pic else []) + ["-c", str(src), "-o", str(obj)],
               TREE / "firmware_sim")
    if res.returncode != 0:
        first = [ln for ln in res.stdout.splitlines() if "error" in ln][:1]
        return (first[0] if first else res.stdout.strip()[-200:]).split("error: ")[-1]
    return None


def _link(program, replace=None):
    """Link a test program from the baseline objects, one of them replaced."""
    fw = TREE / "firmware_sim"
    if program == "co_test":
        rels = [p.relative_to(fw).as_posix() for p in sorted(fw.glob("canopen/co_*.c")) +
                sorted(fw.glob("canopen/tests/*.c"))] + ["build/gen/od_table.c"]
    else:
        rels = [p.relative_to(fw).as_posix() for p in sorted(fw.glob("core/*.c")) + sorted(fw.glob("plant/*.c"))]
        rels.append(f"tests/{program}.c")
    objs = [str(replace[1]) if replace and rel == replace[0] else str(_obj(rel)) for rel in rels]
    out = WORK / "bin" / program
    out.parent.mkdir(exist_ok=True)
    res = _run([CC] + objs + ["-lm", "-o", str(out)], fw)
    if res.returncode != 0:
        return None, res.stdout.strip()[-200:]
    return out, None


def _run_pytest(prog, replace, timeout):
    """A "pytest:FILE ..." program: build/libfwsim.so of the scratch tree linked from the PIC
    objects (the module's rebuilt from its mutated source, in place), the FILEs run there."""
    fw = TREE / "firmware_sim"
    rels = [p.relative_to(fw).as_posix() for p in sorted(fw.glob("core/*.c")) + sorted(fw.glob("plant/*.c"))]
    objs = []
    for rel in rels:
        if replace and rel == replace[0]:
            obj = WORK / "mutant.pic.o"
            err = _compile(rel, fw / rel, obj, pic=True)
            if err:
                return "not-viable", f"compiler (-fPIC): {err}"
            objs.append(str(obj))
        else:
            objs.append(str(_obj(rel, pic=True)))
    lib = fw / "build" / "libfwsim.so"
    res = _run([CC, "-shared", "-o", str(lib)] + objs + ["-lm"], fw)
    if res.returncode != 0:
        return "not-viable", f"link: {res.stdout.strip()[-200:]}"
    # (tests/conftest.py would rebuild the scratch tree's products with make: they are
    # this harness's own, made just above)
    env = dict(os.environ, FFTUNE_TEST_NO_REBUILD="1", PYTHONDONTWRITEBYTECODE="1")
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
           "-W", "ignore", f"--rootdir={TREE}"] + [str(TREE / f) for f in prog.split(":", 1)[1].split()]
    try:
        res = subprocess.run(cmd, cwd=TREE, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                             text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "killed", f"{prog}: timeout"
    if res.returncode == 0:
        return "survived", ""
    if res.returncode in (1, 2) or res.returncode < 0:     # a failure, an error, a crash
        return "killed", f"{prog}: {'crash' if res.returncode < 0 else 'failed'}"
    raise MutationError(f"mutation: {prog}: pytest exit status {res.returncode}: "
                        f"{res.stdout.strip().splitlines()[-1:]}")


def _run_tests(programs, replace, timeout):
    """'killed' / 'survived' (+ detail) / 'not-viable' (link failure)."""
    for prog in programs:
        if prog.startswith("pytest:"):
            verdict, detail = _run_pytest(prog, replace, timeout)
            if verdict != "survived":
                return verdict, detail
            continue
        exe, err = _link(prog, replace)
        if exe is None:
            return "not-viable", f"link: {err}"
        try:
            res = _run([str(exe)], TREE / "firmware_sim", timeout=timeout)
        except subprocess.TimeoutExpired:
            return "killed", f"{prog}: timeout"
        if res.returncode != 0:
            how = "crash" if res.returncode < 0 else "failed"
            return "killed", f"{prog}: {how}"
    return "survived", ""


# --------------------------------------------------------------------------- driver

def _digest(module):
    """What a module's results depend on, as (code, tests): every source linked into its
    test programs, the generator inputs and this harness; and the test programs with their
    data. Only the tests changed: the killed mutants stay killed (tests are added, not
    weakened, here; --restart runs all again), the survivors are run again."""
    if module.startswith("canopen/"):
        code_globs = ["canopen/*.c", "canopen/*.h", "core/drv.h", "tools/odgen.py"]
        test_globs, code_extra, test_extra = ["canopen/tests/*"], [ROOT / "configs" / "od.yaml"], []
    else:
        code_globs = ["core/*.c", "core/*.h", "plant/*.c", "plant/*.h", "tools/odgen.py"]
        test_globs = ["tests/test_core.c", "tests/test_plant.c", "tests/th.h"]
        code_extra = [ROOT / "configs" / "od.yaml"]
        test_extra = [ROOT / "tests" / "vectors" / "multisine_vectors.json"]
        test_extra += [ROOT / f for prog in MODULES[module] for f in PYTEST_FILES.get(prog, [])]

    def digest(globs, extra):
        h = hashlib.sha256()
        h.update(HARNESS_VERSION.encode())
        for p in sorted({q for g in globs for q in FW.glob(g)}) + extra:
            if p.is_file():
                h.update(p.relative_to(ROOT).as_posix().encode())
                h.update(p.read_bytes())
        return h.hexdigest()
    return digest(code_globs, code_extra), digest(test_globs, test_extra)


def _state_path(module):
    return WORK / (module.replace("/", "__") + ".json")


def _load_state(module, restart, digest):
    """Kept results: all of them when nothing changed; the killed and not viable ones when
    only the tests changed (the survivors are run again); none when the code changed."""
    path = _state_path(module)
    code, tests = digest
    if not restart and path.exists():
        state = json.loads(path.read_text())
        if state.get("code_digest") == code:
            if state.get("tests_digest") != tests:
                again = [k for k, r in state["results"].items() if r["outcome"] == "survived"]
                for k in again:
                    del state["results"][k]
                print(f"mutation: {module}: the tests changed: {len(again)} survivor(s) run "
                      f"again, the killed mutants kept", flush=True)
                state["tests_digest"] = tests
                path.write_text(json.dumps(state, indent=0))
            return state
    return {"code_digest": code, "tests_digest": tests, "results": {}}


def run_module(module, deadline, restart, digest):
    state = _load_state(module, restart, digest)
    fw = TREE / "firmware_sim"
    source = (fw / module).read_text()
    lines = source.split("\n")
    todo = [(ln, col, op, new) for ln, col, op, new in mutants_of(source)
            if f"{ln}:{col}:{op}" not in state["results"]]
    # a fixed random order: a run cut short by its budget is a fair sample of the module
    random.Random(module).shuffle(todo)
    if not todo:
        return state
    programs = MODULES[module]
    # baseline: the unmutated module passes its tests (and gives the time limit)
    t0 = time.monotonic()
    verdict, detail = _run_tests(programs, None, timeout=120)
    if verdict != "survived":
        raise MutationError(f"mutation: {module}: the C tests fail on the unmutated code ({detail})")
    limit = max(10.0, 20 * (time.monotonic() - t0))
    scratch = WORK / "mutant.c"
    obj = WORK / "mutant.o"
    try:
        for ln, col, op, new in todo:
            if time.monotonic() > deadline:
                break
            mutated = lines[:ln - 1] + [new] + lines[ln:]
            (fw / module).write_text("\n".join(mutated))   # compiled in place: its #includes
            err = _compile(module, fw / module, obj)
            if err:
                verdict, detail = "not-viable", f"compiler: {err}"
            else:
                verdict, detail = _run_tests(programs, (module, obj), limit)
            state["results"][f"{ln}:{col}:{op}"] = {
                "line": ln, "operator": op, "original": lines[ln - 1].strip(),
                "mutated": new.strip(), "outcome": verdict, "detail": detail}
            _state_path(module).write_text(json.dumps(state, indent=0))
    finally:
        (fw / module).write_text(source)
        scratch.unlink(missing_ok=True)
    return state


def report(module):
    rep = ModuleReport(module)
    path = _state_path(module)
    source = (FW / module).read_text()
    sites = mutants_of(source)
    state = json.loads(path.read_text()) if path.exists() else {"results": {}}
    code, tests = _digest(module)
    if state.get("code_digest") != code:
        state = {"results": {}}
        rep.note = "not run on the present code yet"
    elif state.get("tests_digest") != tests:
        state = {"results": {k: r for k, r in state["results"].items() if r["outcome"] != "survived"}}
        rep.note = "the tests changed since the last run: its survivors count as pending"
    name = Path(module).name
    lines = source.split("\n")
    for ln, col, op, new in sites:
        r = state["results"].get(f"{ln}:{col}:{op}")
        if r is None:
            rep.mutants.append(Mutant(name, ln, op, lines[ln - 1].strip(), new.strip(), "pending"))
        else:
            rep.mutants.append(Mutant(name, ln, op, r["original"], r["mutated"], r["outcome"],
                                      r["detail"]))
    return rep


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--modules", metavar="LIST",
                    help="only these modules (space or comma separated, as MUTATION_MODULES; "
                         "the other driver's names are skipped); default: all")
    ap.add_argument("--module", action="append", default=[], help="one module (repeatable)")
    ap.add_argument("--budget", type=float, default=float(os.environ.get("MUTATION_BUDGET", 3600)),
                    help="seconds for this run (default 3600); the next run continues")
    ap.add_argument("--report-only", action="store_true", help="print the scores, run nothing")
    ap.add_argument("--restart", action="store_true", help="forget earlier results")
    args = ap.parse_args(argv)
    spec = " ".join(args.module + ([args.modules] if args.modules else [])) or None
    try:
        modules = pick_modules(spec, MODULES)
    except MutationError as exc:
        fail(str(exc))
    if not modules:
        return 0                      # MUTATION_MODULES names only the other driver's modules
    if not args.report_only and shutil.which(CC) is None:
        fail(f"mutation: C compiler {CC!r} not found (set CC, or install gcc: make system-deps)")
    signal.signal(signal.SIGTERM, signal.default_int_handler)   # restore the source on a stop
    def run():
        deadline = time.monotonic() + args.budget
        WORK.mkdir(parents=True, exist_ok=True)
        lock = open(WORK / "lock", "w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise MutationError(f"mutation: another C mutation run uses {WORK} (one at a time)")
        digests = {m: _digest(m) for m in modules}   # of the code copied just below
        _prepare_tree()
        for module in modules:
            if time.monotonic() > deadline:
                break
            announce(module, deadline)
            run_module(module, deadline, args.restart, digests[module])
    return run_and_report(None if args.report_only else run, modules, report)

if __name__ == "__main__":
    sys.exit(main())
