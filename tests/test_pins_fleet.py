"""Each column of the fleet table (host/fleet.py) pinned to the one field of a session's
results it reports (issue 33): a results dict with a distinct value in every field, so a
column filled from its neighbour (the even HOSIDF level from the odd one, the noise level
from the nonlinear one, the ratio's std at K_fc* from the one at 0) fails. No drive, no
Dask: fast (the mutation selection of host/fleet.py runs this file first).
"""
import math

import pytest
import yaml

from fftune.analysis.errors import FftuneError
from fftune.host import fleet

LEVELS = [
    {"rms_requested": 0.75, "summary_db": {"nl_re_output_db": -21.5, "noise_re_output_db": -48.25,
                                           "odd_re_output_db": -22.75, "even_re_output_db": -37.125}},
    {"rms_requested": 2.5, "summary_db": {"nl_re_output_db": -14.0, "noise_re_output_db": -55.5,
                                          "odd_re_output_db": -15.25, "even_re_output_db": -33.0}},
    {"rms_requested": 4.25, "summary_db": {"nl_re_output_db": -9.5, "noise_re_output_db": float("nan"),
                                           "odd_re_output_db": -11.0}},          # (even missing)
]
# the K_fc the search sent are float32: 0.0 and the verification's 0.3129 as sent
K_VER = 0.3129
K_VER_SENT = 0.31290000677108765
EVALS = [{"k_fc": 0.0, "ratio_std": 0.0061}, {"k_fc": 0.2, "ratio_std": 0.0042},
         {"k_fc": K_VER_SENT, "ratio_std": 0.00031}, {"k_fc": 0.3135, "ratio_std": 0.0009},
         {"k_fc": None, "ratio_std": 0.5}]
RESULTS = {
    "detect": {"verdict": "odd nonlinear (friction)", "levels": LEVELS, "bla_max_change_over_levels_db": 1.75},
    "quantify": {"max_odd_relative_level": 0.153, "max_even_relative_level": 0.0212},
    "tune": {"k_fc_star": 0.3127, "ratio_at_zero": 0.141, "ratio_at_k_fc_star": 0.0083,
             "true_coulomb_v": 0.3, "search": {"sigma_v": 0.0024, "converged": True,
                                               "stop_reason": "bracket below 2 sigma",
                                               "verification_k_fc": K_VER, "experiments": 7,
                                               "evaluations": EVALS}},
}
# column -> its value, written out from RESULTS above by hand
EXPECTED = {
    "detect_verdict": "odd nonlinear (friction)",
    "bla_rms_levels": [0.75, 2.5, 4.25],
    "bla_nl_re_output_db": [-21.5, -14.0, -9.5],
    "bla_noise_re_output_db": [-48.25, -55.5, None],        # (not finite: None)
    "bla_odd_re_output_db": [-22.75, -15.25, -11.0],
    "bla_even_re_output_db": [-37.125, -33.0, None],        # (missing: None)
    "bla_max_change_db": 1.75,
    "hosidf_max_odd_rel": 0.153, "hosidf_max_even_rel": 0.0212,
    "k_fc_star": 0.3127, "k_fc_sigma": 0.0024, "k_fc_converged": True,
    "tune_stop_reason": "bracket below 2 sigma", "ratio_at_zero": 0.141, "ratio_at_zero_std": 0.0061,
    "ratio_at_k_fc_star": 0.0083, "ratio_at_k_fc_star_std": 0.00031, "tune_experiments": 7,
    "k_fc_true": 0.3,
}


def _row():
    return fleet._empty_row("/x/captures", "captures")


def test_every_column_from_its_own_field():
    row = _row()
    fleet._fill_results(row, RESULTS)
    for col, want in EXPECTED.items():
        assert row[col] == want, col
    # the columns the results do not fill stay as the empty row has them
    untouched = set(name for name, _ in fleet.COLUMNS) - set(EXPECTED)
    assert {c: row[c] for c in untouched} == {c: _row()[c] for c in untouched}
    # every column of the table is either filled from the results or a row fact
    assert untouched == {"source", "kind", "machine", "axis", "node_id", "date", "status", "reason", "runs"}


def test_each_step_fills_only_its_columns():
    groups = {"detect": [c for c in EXPECTED if c.startswith(("bla_", "detect_"))],
              "quantify": ["hosidf_max_odd_rel", "hosidf_max_even_rel"],
              "tune": [c for c in EXPECTED if not c.startswith(("bla_", "detect_", "hosidf_"))]}
    for step, cols in groups.items():
        row = _row()
        fleet._fill_results(row, {step: RESULTS[step]})
        filled = {c for c in EXPECTED if row[c] is not None}
        assert filled == set(cols), step


def test_ratio_std_only_at_a_measured_point():
    """The std columns read the evaluation at K_fc = 0 and the one AT the verification's K_fc
    (as sent, float32), not the nearest one when none is there."""
    t = {k: v for k, v in RESULTS["tune"].items()}
    s = dict(t["search"], evaluations=[e for e in EVALS if e["k_fc"] not in (0.0, K_VER_SENT)])
    row = _row()
    fleet._fill_results(row, {"tune": dict(t, search=s)})
    # 0.2 is 0.2 away from 0; 0.3135 is 6e-4 (1.9e-3 relative) from 0.3129: neither is "at"
    assert row["ratio_at_zero_std"] is None and row["ratio_at_k_fc_star_std"] is None
    # within the float32 rounding of K_fc (1e-6 V below 1 V, 1e-6 relative above): found
    s = dict(t["search"], evaluations=[{"k_fc": K_VER + 0.9e-6, "ratio_std": 0.0007},
                                       {"k_fc": 0.9e-6, "ratio_std": 0.0051}])
    row = _row()
    fleet._fill_results(row, {"tune": dict(t, search=s)})
    assert row["ratio_at_k_fc_star_std"] == 0.0007 and row["ratio_at_zero_std"] == 0.0051
    s = dict(t["search"], evaluations=[{"k_fc": K_VER + 1.1e-6, "ratio_std": 0.0007},
                                       {"k_fc": 1.1e-6, "ratio_std": 0.0051}])
    row = _row()
    fleet._fill_results(row, {"tune": dict(t, search=s)})
    assert row["ratio_at_k_fc_star_std"] is None and row["ratio_at_zero_std"] is None
    s = dict(t["search"], verification_k_fc=2.5, evaluations=[{"k_fc": 2.5 * (1 + 0.9e-6), "ratio_std": 0.0004},
                                                              {"k_fc": 0.0, "ratio_std": 0.0051}])
    row = _row()
    fleet._fill_results(row, {"tune": dict(t, search=s)})
    assert row["ratio_at_k_fc_star_std"] == 0.0004
    # no verification experiment: no std at K_fc*; an unconverged search: False, its reason
    s = dict(t["search"], verification_k_fc=None, converged=False, stop_reason="max experiments",
             experiments=None)
    row = _row()
    fleet._fill_results(row, {"tune": dict(t, search=s)})
    assert row["ratio_at_k_fc_star_std"] is None and row["ratio_at_zero_std"] == 0.0061
    assert row["k_fc_converged"] is False and row["tune_stop_reason"] == "max experiments"
    assert row["tune_experiments"] == 0


def test_numbers_that_are_not_finite_are_none():
    assert fleet._num(float("inf")) is None and fleet._num(float("nan")) is None
    assert fleet._num("0.25") == 0.25 and fleet._num("x") is None and fleet._num(None) is None
    assert fleet._num(-3) == -3.0 and isinstance(fleet._num(-3), float)
    row = _row()
    fleet._fill_results(row, {"quantify": {"max_odd_relative_level": math.inf,
                                           "max_even_relative_level": -0.0}})
    assert row["hosidf_max_odd_rel"] is None and row["hosidf_max_even_rel"] == 0.0


def test_the_table_keeps_each_column_apart():
    """Through the arrow schema (every row has every column, in the fixed order)."""
    pytest.importorskip("pyarrow", reason="fleet's table needs pyarrow (fftune[fleet]; make setup installs it)")
    row = _row()
    fleet._fill_results(row, RESULTS)
    row.update(machine="m1", axis="x", node_id=5, date="2026-01-01T00:00:00", status="ok", runs=31)
    other = _row()
    other.update(reason="no readable capture: a.h5: bad", machine="m2")
    table = fleet.arrow_table([row, other])
    assert table.column_names == [name for name, _ in fleet.COLUMNS]
    back = table.to_pylist()
    for col, want in EXPECTED.items():
        assert back[0][col] == want, col
        assert back[1][col] is None, col
    assert back[0]["runs"] == 31 and back[1]["status"] == "error" and back[1]["reason"].startswith("no readable")


def test_runs_column_counts_resumed_and_measured_runs():
    class Session:
        counts = {"resumed": 3, "measured": 4}
    row = fleet._run_steps(Session(), [], _row())
    assert row["runs"] == 7 and row["status"] == "error" and row["reason"] == ""


def test_names_from_the_folders_without_results_yaml_and_a_reason_when_it_is_not_a_mapping(tmp_path):
    d = tmp_path / "mach9" / "ax3" / "2026-03-04" / "captures"
    d.mkdir(parents=True)
    machine, axis, node_id, truth, out_dir, display = fleet._names_for(str(d))
    assert (machine, axis, node_id, truth, out_dir) == ("mach9", "ax3", None, None, str(d.parent))
    assert display == "mach9 / ax3"
    (d.parent / "results.yaml").write_text("- not\n- a mapping\n")
    # a damaged results.yaml is the row's reason (the fleet run goes on), never a silent guess
    with pytest.raises(FftuneError, match="expected a mapping at the top level, got list"):
        fleet._names_for(str(d))
    (d.parent / "results.yaml").write_text(yaml.safe_dump({"axis": {"name": "x", "machine": "m", "node_id": 4},
                                                           "drive": {"plant_truth": {"sim_fc_volt": 0.2}}}))
    assert fleet._names_for(str(d))[:4] == ("m", "x", 4, {"sim_fc_volt": 0.2})
