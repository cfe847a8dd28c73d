"""The mutation tool's per-test coverage map (tools/mutation/testmap.py): which tests a
mutant runs. A wrong map lets a mutant skip the test that kills it (a survivor that is not
one) or, worse, the whole point of the map: it must only narrow where it can vouch."""
import sys
import textwrap
from pathlib import Path

import coverage
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools" / "mutation"))
import testmap  # noqa: E402

MODULE = textwrap.dedent('''\
    LIMIT = 3


    def f(x):
        y = (x +
             1)
        return y * LIMIT


    def g(x):
        if x > 0:
            return -x
        return x
''')
NODES = ["tests/test_a.py::test_f", "tests/test_a.py::test_g",
         "tests/test_b.py::test_uses_fixture", "tests/test_b.py::test_reads_fixture"]


@pytest.fixture
def module_and_data(tmp_path):
    mod = tmp_path / "m.py"
    mod.write_text(MODULE)
    data = coverage.CoverageData(basename=str(tmp_path / "cov.data"))
    path = str(mod)
    data.set_context("")                                    # import time
    data.add_lines({path: [1, 4, 10]})
    data.set_context("tests/test_a.py::test_f|run")
    data.add_lines({path: [5, 6, 7]})                      # (6: inside the statement of line 5)
    data.set_context("tests/test_a.py::test_g|run")
    data.add_lines({path: [11, 13]})
    data.set_context("tests/test_b.py::test_uses_fixture|setup")
    data.add_lines({path: [11, 12]})
    data.write()
    return mod, tmp_path / "cov.data"


def _select(tmp_path, mod, data_file, mutated):
    m = testmap.build(data_file, mod, NODES)
    testmap.save(tmp_path / "map.json", MODULE, m)
    mod.write_text(mutated)
    return testmap.select(tmp_path / "map.json", mod)


def test_map_rules(module_and_data):
    mod, data_file = module_and_data
    m = testmap.build(data_file, mod, NODES)["lines"]
    assert m["1"] == m["4"] == m["10"] == testmap.ALL        # import time: everything
    assert m["5"] == ["tests/test_a.py::test_f"]             # line 6 folded into its statement
    assert "6" not in m
    assert m["7"] == ["tests/test_a.py::test_f"]
    # a fixture's set-up selects every test of its file, in run order
    assert m["12"] == ["tests/test_b.py::test_uses_fixture", "tests/test_b.py::test_reads_fixture"]
    assert m["11"] == ["tests/test_a.py::test_g", "tests/test_b.py::test_uses_fixture",
                       "tests/test_b.py::test_reads_fixture"]
    assert m["13"] == ["tests/test_a.py::test_g"]


@pytest.mark.parametrize("old,new,expected", [
    ("    return y * LIMIT", "    return y / LIMIT", ["tests/test_a.py::test_f"]),
    ("         1)", "         2)", ["tests/test_a.py::test_f"]),              # 2nd line of a statement
    ("        return -x", "        return x",
     ["tests/test_b.py::test_uses_fixture", "tests/test_b.py::test_reads_fixture"]),
    ("    if x > 0:", "    if x >= 0:",
     ["tests/test_a.py::test_g", "tests/test_b.py::test_uses_fixture", "tests/test_b.py::test_reads_fixture"]),
    ("LIMIT = 3", "LIMIT = 4", None),                                        # import time
    # an inserted line: the statements either side of it
    ("        return -x\n", "        return -x\n        x = 1\n",
     ["tests/test_a.py::test_g", "tests/test_b.py::test_uses_fixture", "tests/test_b.py::test_reads_fixture"]),
    ("    return x\n", "    return x\n    x = 1\n", None),                # after the last: unknown
])
def test_a_mutant_runs_the_tests_that_reach_it(module_and_data, tmp_path, old, new, expected):
    mod, data_file = module_and_data
    assert MODULE.count(old) == 1
    assert _select(tmp_path, mod, data_file, MODULE.replace(old, new)) == expected


def test_a_statement_no_test_ran_in_this_process_runs_everything(tmp_path):
    """(executed in a subprocess, or never): the map cannot vouch, the whole selection runs."""
    mod = tmp_path / "m.py"
    mod.write_text(MODULE)
    data = coverage.CoverageData(basename=str(tmp_path / "cov.data"))
    data.set_context("tests/test_a.py::test_f|run")
    data.add_lines({str(mod): [5, 7]})
    data.write()
    assert _select(tmp_path, mod, tmp_path / "cov.data", MODULE.replace("return -x", "return x")) is None
    mod.write_text(MODULE)
    assert _select(tmp_path, mod, tmp_path / "cov.data", MODULE) is None        # no change: everything
