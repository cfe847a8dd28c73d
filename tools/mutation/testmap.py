"""Which tests execute which statement of a module: the per-test coverage map that lets a
mutant run only the tests that can meet it (as mutmut and Stryker do).

Built once per session from one run of the module's test selection under coverage.py with
per-test contexts (pytest-cov ``--cov-context=test``). The rules keep it sound, a mutant
never skips a test that could kill it:

- a statement executed by a test's call ("nodeid|run") selects that test;
- executed in a fixture's set-up or tear-down ("nodeid|setup"/"|teardown") selects every
  test of that test's file (a module-scoped fixture runs once for all of them, and a
  test that only reads its result can be the one that fails);
- executed at import or collection time (no test context), not executed in this process
  at all (a subprocess, a dask worker), or not a statement coverage knows: the whole
  selection runs, as without the map.

A mutant's statements are the original lines its edit changed, each taken to the first
line of its statement (coverage's own parser).
"""
import difflib
import json
from pathlib import Path

ALL = "*"


def build(coverage_file, module_path, node_ids):
    """The map {first line of statement: [node ids] or ALL} of ``module_path`` (the file
    coverage measured) from the coverage data file; ``node_ids`` the selection's tests in
    their run order."""
    import coverage
    from coverage.python import PythonParser

    data = coverage.CoverageData(basename=str(coverage_file))
    data.read()
    measured = [f for f in data.measured_files() if Path(f).resolve() == Path(module_path).resolve()]
    if not measured:
        raise RuntimeError(f"coverage measured nothing of {module_path}")
    parser = PythonParser(text=Path(module_path).read_text(encoding="utf-8"), filename=str(module_path))
    parser.parse_source()
    by_file = {}
    for nid in node_ids:
        by_file.setdefault(nid.split("::", 1)[0], []).append(nid)
    lines = {}
    for lineno, contexts in data.contexts_by_lineno(measured[0]).items():
        first = parser.first_line(lineno)
        entry = lines.setdefault(first, set())
        if entry == ALL:
            continue
        for ctx in contexts:
            nid, _, phase = ctx.rpartition("|")
            if not nid or nid.split("::", 1)[0] not in by_file:
                lines[first] = ALL                      # import or collection time
                break
            entry.update([nid] if phase == "run" else by_file[nid.split("::", 1)[0]])
    order = {nid: i for i, nid in enumerate(node_ids)}
    return {"order": list(node_ids),
            "lines": {str(k): (v if v == ALL else sorted(v, key=lambda n: order.get(n, len(order))))
                      for k, v in lines.items()}}


def save(path, original_text, test_map):
    Path(path).write_text(json.dumps(dict(test_map, original=original_text)))


def select(map_path, module_path):
    """The node ids the mutant now in ``module_path`` must run, in order; None: the whole
    selection (a statement the map cannot vouch for)."""
    from coverage.python import PythonParser

    m = json.loads(Path(map_path).read_text())
    original = m["original"].splitlines(keepends=True)
    mutated = Path(module_path).read_text(encoding="utf-8").splitlines(keepends=True)
    changed = set()
    for tag, i1, i2, _, _ in difflib.SequenceMatcher(None, original, mutated, autojunk=False).get_opcodes():
        if tag == "equal":
            continue
        # the original lines replaced or deleted; an insertion: the lines either side of it
        changed.update(range(i1 + 1, i2 + 1) if i2 > i1 else (i1, i1 + 1))
    changed.discard(0)
    if not changed:
        return None
    parser = PythonParser(text=m["original"], filename=str(module_path))
    parser.parse_source()
    wanted = set()
    for line in changed:
        tests = m["lines"].get(str(parser.first_line(line)))
        if tests is None or tests == ALL:
            return None
        wanted.update(tests)
    return [nid for nid in m["order"] if nid in wanted]
