"""The fleet's summary and report numbers a person reads (host/fleet.py; issue 33's
hand-written bug audit, docs/testing.md): the change of K_fc* over an axis' analyses in
percent and in sigma, the report's cells each in its column, a capture folder with a
damaged file beside readable ones a partial row naming it. Unequal values throughout, the
expected numbers computed here from the inputs (not read back from the code). Fast: one
small session on the Python test double (about a second) for the damaged-file case.
"""
import html
import math
import re
import shutil

import pytest

from fftune.host import fleet
from fftune.host.pipeline import run_pipeline
from host_fixtures import FakeDriveForTests
from test_host_experiments import _cfg


def _row(**kw):
    row = fleet._empty_row(kw.pop("source", "/f/m/x/captures"), "captures")
    row.update(status="ok", reason="")
    row.update(kw)
    return row


# one axis analysed three times (out of date order in the list) with unequal sigmas, and a
# second axis once; a partial row counts (it has a K_fc*), an error row and an ok row
# without a K_fc* do not (both are counted as rows without one)
ROWS = [
    _row(machine="m1", axis="x", date="2026-03-01T08:00:00", k_fc_star=0.3391, k_fc_sigma=0.0041,
         source="/f/m1/x/c"),
    _row(machine="m1", axis="x", date="2026-01-01T08:00:00", k_fc_star=0.2953, k_fc_sigma=0.0017,
         source="/f/m1/x/a"),
    _row(machine="m1", axis="x", date="2026-02-01T08:00:00", k_fc_star=0.3100, k_fc_sigma=0.0090,
         status="partial", reason="quantify: x", source="/f/m1/x/b"),
    _row(machine="m1", axis="y", date="2026-02-11T10:30:00", k_fc_star=0.5012, k_fc_sigma=0.0023,
         source="/f/m1/y"),
    _row(machine="m1", axis="z", status="error", reason="no readable capture", source="/f/m1/z"),
    # analysed without a tune (detect and quantify only): ok, but no K_fc* either
    _row(machine="m1", axis="q", date="2026-02-12T09:00:00", detect_verdict="linear", source="/f/m1/q"),
]


def test_summary_change_in_percent_of_the_first_and_in_sigma_of_both_ends():
    items = fleet.summary_items(ROWS)
    x = [t for t in items if t.startswith("m1 / x")]
    assert len(x) == 1
    # latest 0.3391 +- 0.0041 (March), first 0.2953 +- 0.0017 (January): the middle one
    # (sigma 0.0090) plays no part
    first, last, s_first, s_last = 0.2953, 0.3391, 0.0017, 0.0041
    pct = 100.0 * (last - first) / first                       # +14.83 %
    n_sigma = abs(last - first) / math.sqrt(s_first ** 2 + s_last ** 2)   # 9.9 sigma
    assert "K_fc* = 0.3391 V +- 0.0041 V" in x[0] and "2026-03-01 08:00 UTC" in x[0]
    assert f"{pct:+.1f} % since 2026-01-01 08:00 UTC over 3 analyses" in x[0], x[0]
    assert f"({n_sigma:.1f} sigma)" in x[0], x[0]
    # (the wrong divisors give other figures: over the last value +12.9 %, the last sigma
    # alone 10.7 sigma, the first alone 25.8 sigma)
    assert f"{100.0 * (last - first) / last:+.1f} %" not in x[0]
    assert f"({abs(last - first) / s_last:.1f} sigma)" not in x[0]
    y = [t for t in items if t.startswith("m1 / y")]
    assert y == ["m1 / y: K_fc* = 0.5012 V +- 0.0023 V on object 0x2000:04 (latest analysis, "
                 "2026-02-11 10:30 UTC)"]            # (one analysis: no change figure)
    assert items[-1] == "2 of 6 rows without a K_fc* (the table says why)"
    assert not [t for t in items if t.startswith("m1 / q") or t.startswith("m1 / z")]


def test_summary_change_without_sigmas_has_no_sigma_figure():
    rows = [_row(machine="m", axis="a", date="2026-01-01T00:00:00", k_fc_star=0.4, k_fc_sigma=None),
            _row(machine="m", axis="a", date="2026-01-02T00:00:00", k_fc_star=0.3, k_fc_sigma=None)]
    text = fleet.summary_items(rows)[0]
    assert "-25.0 % since 2026-01-01 00:00 UTC over 2 analyses" in text and "sigma)" not in text


def _cells(page):
    """The K_fc* table's data rows as lists of cell texts."""
    table = page.split("<h2>K_fc* per axis and date</h2>", 1)[1].split("</table>", 1)[0]
    rows = re.findall(r"<tr>(.*?)</tr>", table, flags=re.S)
    return [[html.unescape(c) for c in re.findall(r"<td>(.*?)</td>", r, flags=re.S)] for r in rows[1:]]


def test_report_table_each_cell_in_its_column(tmp_path):
    rows = [_row(machine="m1", axis="x", node_id=12, date="2026-03-01T08:00:00", k_fc_star=0.3391,
                 k_fc_sigma=0.0041, k_fc_true=0.3125, ratio_at_zero=0.1415, ratio_at_k_fc_star=0.00832,
                 source="/f/m1/x/c"),
            _row(machine="m1", axis="w", node_id=3, date="2026-03-02T08:00:00", k_fc_converged=False,
                 tune_stop_reason="max experiments", ratio_at_zero=0.2, status="partial",
                 reason="tune: partial capture", source="/f/m1/w")]
    page = open(fleet.write_summary_html(rows, str(tmp_path), [str(tmp_path / "fleet.csv")], [], [("c", "/f")]),
                encoding="utf-8").read()
    cells = _cells(page)
    assert cells[0] == ["m1 / x", "12", "2026-03-01T08:00:00", "ok", "0.3391 V +- 0.0041 V", "0.3125 V",
                        "14.1 % -> 0.832 %", "(/f/m1/x/c)"]
    assert cells[1] == ["m1 / w", "3", "2026-03-02T08:00:00", "partial", "not converged: max experiments", "-",
                        "20 % -> -", "tune: partial capture (/f/m1/w)"]
    assert "2 rows: 1 ok, 1 partial, 0 not analysed" in page


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet2")
    cfg = _cfg()
    cfg["detect"]["enabled"] = cfg["quantify"]["enabled"] = False
    cfg["tune"]["sweep"]["points"] = 0
    cfg["tune"]["viscous"]["enabled"] = False
    d = FakeDriveForTests(fc_volt=0.3, fv_volt=0.02, noise_std=1e-5)
    d.enable()
    run_pipeline(d, cfg, str(root / "m" / "x"), log=lambda s: None, figures=False)
    return root


def test_a_damaged_file_beside_readable_captures_makes_the_row_partial_naming_it(small_run, tmp_path):
    """The first capture file (in name order) unreadable, the others fine: the steps are
    analysed from the readable ones, and the row says partial with the damaged file's name
    (not ok: a file of the session was lost)."""
    good = fleet.analyse_captures(str(small_run / "m" / "x" / "captures"))[0]
    assert good["status"] == "ok" and good["reason"] == "" and good["k_fc_star"] is not None
    copy = tmp_path / "m" / "x"
    shutil.copytree(small_run / "m" / "x", copy)
    (copy / "captures" / "a-lost.stats.json").write_text("{not json")
    row = fleet.analyse_captures(str(copy / "captures"))[0]
    assert row["status"] == "partial", row
    assert row["reason"].startswith("a-lost.stats.json: "), row["reason"]
    assert row["k_fc_star"] == good["k_fc_star"] and row["runs"] == good["runs"]


@pytest.mark.parametrize("v, ok", [(1, True), (127, True), (64, True), (0, False), (128, False), (True, False),
                                   (5.0, False)])
def test_node_id_from_results_one_to_127_inclusive(v, ok):
    from fftune.analysis.errors import FftuneError

    if ok:
        assert fleet._node_id(v, "r.yaml: key 'axis.node_id'") == v
    else:
        with pytest.raises(FftuneError) as exc:
            fleet._node_id(v, "r.yaml: key 'axis.node_id'")
        assert str(exc.value) == f"r.yaml: key 'axis.node_id': expected a node id 1..127, got {v!r}"
    assert fleet._node_id(None, "x") is None


@pytest.mark.parametrize("runs, ok", [(2 ** 63 - 1, True), (-(2 ** 63), True), (2 ** 63, False),
                                      (-(2 ** 63) - 1, False), (2 ** 62, True)])
def test_int64_columns_hold_exactly_the_int64_range(runs, ok):
    """(the lead's mutation run: _INT64's bounds)"""
    row = _row(runs=runs, reason="")
    out = fleet.checked_row(row)
    if ok:
        assert out["runs"] == runs and out["status"] == "ok" and out["reason"] == ""
    else:
        text = repr(runs)
        short = text if len(text) <= 40 else text[:37] + "..."
        assert out["runs"] is None and out["status"] == "error"
        assert out["reason"] == f"column runs: {short} is not int64"        # (no leading '; ')


def test_checked_row_keeps_the_rows_own_reason_first():
    out = fleet.checked_row(_row(status="partial", reason="quantify: lost", k_fc_star="0.3", runs=True))
    assert out["status"] == "error" and out["k_fc_star"] is None and out["runs"] is None
    assert out["reason"] == "quantify: lost; column runs: True is not int64; column k_fc_star: '0.3' is not double"


def test_short_values_in_reasons_at_most_40_characters():
    assert fleet._short("a" * 38) == "'" + "a" * 38 + "'"                  # 40 characters: whole
    assert fleet._short("a" * 39) == "'" + "a" * 36 + "..."                # 41: cut to 37 + ...
    assert len(fleet._short(list(range(100)))) == 40


@pytest.mark.parametrize("n_items, slots, sizes", [(10, 2, [3, 3, 3, 1]), (3, 4, [1, 1, 1]), (9, 1, [5, 4]),
                                                   (0, 3, [])])
def test_batches_two_per_worker_slot_in_order(n_items, slots, sizes):
    items = list(range(n_items))
    got = fleet.batches(items, slots)
    assert [len(b) for b in got] == sizes and [x for b in got for x in b] == items


def test_dates_that_are_not_dates_are_none():
    assert fleet._date("2026-02-11T10:30:00+02:00").isoformat() == "2026-02-11T08:30:00"
    assert fleet._date("not a date") is None and fleet._date(None) is None


def test_a_folder_of_unreadable_captures_is_a_row_naming_them(tmp_path):
    d = tmp_path / "m" / "x" / "captures"
    d.mkdir(parents=True)
    (d / "tune-001.stats.json").write_text("{broken")
    (d / "tune-002.stats.json").write_text("[]")
    row = fleet.analyse_captures(str(d))[0]
    assert row["status"] == "error" and (row["machine"], row["axis"]) == ("m", "x")
    assert row["reason"].startswith("no readable capture: tune-001.stats.json: "), row["reason"]
    assert "; tune-002.stats.json: " in row["reason"]


def test_a_refused_scheduler_port_says_why_in_words():
    import socket

    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    from fftune.analysis.errors import FftuneError
    with pytest.raises(FftuneError) as exc:
        fleet.probe_scheduler(f"tcp://127.0.0.1:{port}", timeout_s=2.0)
    assert str(exc.value) == f"--scheduler tcp://127.0.0.1:{port}: cannot connect (Connection refused)"
