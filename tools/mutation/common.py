"""Shared parts of `make mutation`: the equivalent-mutant list and the per-module report.

A mutant is identified by what a reader sees: the module's file name, the original source
line and the mutated line (both stripped of surrounding white space). Line numbers move as
the code changes; the text pair does not (two identical lines with the same mutation are
one entry, which is what a reader of the list means anyway).

The list of equivalent mutants (mutations that cannot change behaviour) is the table under
the heading "Equivalent mutants" in docs/testing.md: one source, read here and by people.
"""
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TESTING_DOC = ROOT / "docs" / "testing.md"
EQUIV_HEADING = "## Equivalent mutants"


class MutationError(Exception):
    """A user-facing failure: printed as one `fftune: error: ...` line."""


def fail(message):
    print(f"fftune: error: {message}", file=sys.stderr)
    sys.exit(2)


def pick_modules(spec, own):
    """The modules of ``own`` (this driver's names) named in ``spec`` (MUTATION_MODULES: names
    separated by spaces or commas, e.g. "canopen/co_sdo.c analysis/bla.py"; a Python module
    also as "bla" or "bla.py"). Names of the other driver are left to it; a name neither
    driver knows is an error. None (no spec) means all of ``own``."""
    if spec is None:
        return list(own)
    from cmut import MODULES as c_modules
    from pymut import MODULES as py_modules
    known = {m: m for m in c_modules}
    for short, (path, _) in py_modules.items():
        known.update({short: short, f"{short}.py": short, path: short})
    names = [n for n in re.split(r"[\s,]+", spec.strip()) if n]
    unknown = [n for n in names if n not in known]
    if unknown:
        raise MutationError(
            f"mutation: unknown module {unknown[0]!r} (C: {', '.join(c_modules)}; Python: "
            f"{', '.join(v[0] for v in py_modules.values())})")
    return [m for m in own if m in {known[n] for n in names}]


def announce(name, deadline):
    """One progress line: module ``name`` starts, with the budget left until ``deadline``."""
    print(f"mutation: {name}: running (budget left "
          f"{max(0, deadline - time.monotonic()):.0f} s)", flush=True)


def run_and_report(run, names, report):
    """The shared tail of both tools: check the equivalent-mutant list, ``run()`` the
    mutants (None for a report only), print the scores of ``names`` (``report(name)``).

    A :class:`MutationError` is one error line (exit 2); Ctrl-C or SIGTERM keeps the
    results so far and returns 130. Returns the exit status.
    """
    try:
        equivalents = load_equivalents()
        if run is not None:
            run()
        print_report([report(n) for n in names], equivalents)
    except MutationError as exc:
        fail(str(exc))
    except KeyboardInterrupt:
        print("mutation: stopped; the results so far are kept, run again to continue",
              file=sys.stderr)
        return 130
    return 0


def _split_row(line):
    """Cells of a markdown table row; `\\|` is a literal bar, backticks are dropped."""
    cells = re.split(r"(?<!\\)\|", line.strip().strip("|"))
    return [c.replace("\\|", "|").strip().strip("`").strip() for c in cells]


def load_equivalents(path=TESTING_DOC):
    """{(file name, original line, mutated line): reason} from docs/testing.md.

    Rows of the table after the heading "## Equivalent mutants" (up to the next heading):
    | file | original line | mutated line | why it cannot change behaviour |
    """
    if not path.exists():
        return {}
    equivalents, inside = {}, False
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.startswith("## "):
            inside = line.strip() == EQUIV_HEADING
            continue
        if not inside or not line.lstrip().startswith("|"):
            continue
        cells = _split_row(line)
        if len(cells) != 4 or set(cells[0]) <= set("-: ") or cells[0].lower() == "file":
            continue
        if not cells[3]:
            raise MutationError(f"{path}:{n}: equivalent mutant without a reason")
        equivalents[(cells[0], cells[1], cells[2])] = cells[3]
    return equivalents


@dataclass
class Mutant:
    """One mutant and its outcome: killed, survived, pending or not viable."""

    file: str                 # file name, e.g. "bla.py"
    line: int                 # 1-based line of the mutation (in the code it was run on)
    operator: str
    original: str             # source line, stripped
    mutated: str              # mutated line, stripped
    outcome: str              # "killed" | "survived" | "pending" | "not-viable"
    detail: str = ""          # e.g. "timeout", "crash", the compiler's complaint

    @property
    def key(self):
        return (self.file, self.original, self.mutated)


@dataclass
class ModuleReport:
    name: str                 # e.g. "analysis/bla.py"
    mutants: list = field(default_factory=list)
    note: str = ""

    def counts(self, equivalents):
        viable = [m for m in self.mutants if m.outcome != "not-viable"]
        killed = [m for m in viable if m.outcome == "killed"]
        survived = [m for m in viable if m.outcome == "survived"]
        pending = [m for m in viable if m.outcome == "pending"]
        equiv = [m for m in survived if m.key in equivalents]
        return viable, killed, survived, pending, equiv


def print_report(reports, equivalents, out=sys.stdout):
    """Per module: mutants, killed, survived (equivalent ones apart), score, survivors."""
    rows = []
    for rep in reports:
        viable, killed, survived, pending, equiv = rep.counts(equivalents)
        judged = len(viable) - len(pending) - len(equiv)
        score = 100.0 * len(killed) / judged if judged else float("nan")
        rows.append((rep.name, len(viable), len(killed), len(survived), len(equiv),
                     len(pending), score))
    width = max([len(r[0]) for r in rows] + [6])
    print(f"{'module':<{width}}  mutants  killed  survived  (equivalent)  pending  "
          f"killed/non-equivalent", file=out)
    for name, n, k, s, e, p, score in rows:
        sc = "   n/a" if score != score else f"{score:6.1f} %"
        print(f"{name:<{width}}  {n:7d}  {k:6d}  {s:8d}  {e:12d}  {p:7d}  {sc}", file=out)
    for rep in reports:
        viable, killed, survived, pending, equiv = rep.counts(equivalents)
        real = [m for m in survived if m.key not in equivalents]
        if rep.note:
            print(f"\n{rep.name}: {rep.note}", file=out)
        if real:
            print(f"\n{rep.name}: {len(real)} surviving mutant(s) (need a test, or an entry in "
                  f"docs/testing.md if equivalent):", file=out)
            for m in sorted(real, key=lambda m: (m.line, m.operator)):
                print(f"  {m.file}:{m.line} {m.operator}\n      - {m.original}\n      + "
                      f"{m.mutated}", file=out)
        if pending:
            print(f"\n{rep.name}: {len(pending)} mutant(s) not run yet (time budget): run "
                  f"`make mutation` again to continue", file=out)
