"""The machine's numbers and verdicts without a bus (host/machine.py; issue 33): each field
of an axis' summary entry, the exit status of every mix of outcomes, the printed lines and
the report's table cells, the bus model's figures, the per-axis plants; unequal values
throughout, expected values written out here. Fast (the mutation selection of
host/machine.py runs this file first; the sessions on drive_sim are tests/test_machine.py).
"""
import re

import pytest
import yaml

from fftune.host import machine as mc

AX = {"name": "x2", "node_id": 12}
RESULTS = {"tune": {"k_fc_star": 0.1183, "true_coulomb_v": 0.1157, "k_fc_star_error_re_truth": 0.02247,
                    "search": {"sigma_v": 0.0017, "converged": False, "stop_reason": "max experiments"}},
           "detect": {"verdict": "odd nonlinear"}, "experiments": {"measured": 23, "resumed": 2},
           "time_budget_s": {"total": {"excitation": 41.5, "bus": 2.25, "drive_wait": 39.0}}}


def test_axis_entry_each_field_from_its_own_result():
    e = mc._axis_entry(AX, RESULTS, "unconverged", "not converged: max experiments")
    assert e == {"name": "x2", "node_id": 12, "status": "unconverged", "k_fc_star": 0.1183, "sigma": 0.0017,
                 "k_fc_true": 0.1157, "k_fc_error_re_truth": 0.02247, "converged": False,
                 "stop_reason": "max experiments", "verdict": "odd nonlinear",
                 "experiments": {"measured": 23, "resumed": 2},
                 "time_budget_s": {"excitation": 41.5, "bus": 2.25, "drive_wait": 39.0},
                 "error": "not converged: max experiments", "results": "x2/results.yaml"}
    # no result (a failed axis): its error, no numbers, the truth of the plant if known
    e = mc._axis_entry(AX, error="no SDO answer", truth={"sim_fc_volt": 0.16})
    assert (e["status"], e["error"], e["k_fc_star"], e["sigma"], e["k_fc_true"], e["results"]) == \
        ("failed", "no SDO answer", None, None, 0.16, None)
    # the tune's own truth comes first
    e = mc._axis_entry(AX, RESULTS, "ok", truth={"sim_fc_volt": 0.16})
    assert e["k_fc_true"] == 0.1157


@pytest.mark.parametrize("statuses, code", [
    (["ok", "ok", "ok"], 0), (["ok", "unconverged"], 1), (["unconverged", "unconverged"], 1),
    (["ok", "failed"], 2), (["unconverged", "failed", "ok"], 2), (["cancelled", "ok"], 2),
    (["unconverged", "cancelled"], 2), (["failed"], 2),
])
def test_exit_status_of_every_mix(statuses, code):
    assert mc.exit_code({"axes": [{"status": s} for s in statuses]}) == code


def _summary():
    axes = [mc._axis_entry({"name": "a", "node_id": 5}, RESULTS, "ok"),
            mc._axis_entry({"name": "gh", "node_id": 9}, error="no SDO answer from node 9"),
            dict(mc._axis_entry({"name": "b", "node_id": 7}, {"tune": {"k_fc_star": 0.1585, "search": {"sigma_v": None}}},
                                "ok"), k_fc_true=None)]
    axes[0]["time_budget_s"] = {"excitation": 41.5, "bus": 2.25, "drive_wait": 39.0}
    s = mc.machine_summary({"name": "m7"}, axes, 63.2, "2026-01-02T03:04:05", measure_wall_s=58.1)
    s["finished"] = "2026-01-02T03:05:08"
    return s


def test_summary_lines_say_each_axis_and_the_time():
    lines = mc.summary_lines(_summary(), "out/m7")
    assert lines[0].startswith("fftune machine m7: results in out/m7/")
    a = lines[1].split()
    assert a[:4] == ["a", "node", "5", "ok"]
    # the error re truth computed here: 0.1183 / 0.1157 - 1 = +2.25 %
    assert lines[1].endswith(f"K_fc* = 0.1183 V +- 0.0017 V (truth 0.1157 V, {100 * (0.1183 / 0.1157 - 1):+.2f} %)")
    assert "+2.25 %" in lines[1]
    assert lines[2].split()[:4] == ["gh", "node", "9", "failed"] and lines[2].endswith("no SDO answer from node 9")
    assert lines[3].endswith("K_fc* = 0.1585 V +- nan V")                       # no sigma, no truth
    t = lines[4]
    assert t.startswith("  time: wall 63.2 s (measuring 58.1 s), longest axis' excitation 41.5 s (sum 41.5 s), bus 2.25 s")
    assert t.endswith(f"({100 * 2.25 / 41.5:.1f} % of the longest excitation)") and "(5.4 %" in t


def test_report_table_cells_in_their_columns(tmp_path):
    s = _summary()
    mc.write_machine(str(tmp_path), s)
    back = yaml.safe_load((tmp_path / "results.yaml").read_text())
    assert back["axes"] == s["axes"] and back["time_budget_s"]["total"] == s["time_budget_s"]["total"]
    page = (tmp_path / "report.html").read_text()
    head = re.search(r"<tr><th>(.*?)</th></tr>", page).group(1).split("</th><th>")
    rows = [re.findall(r"<td>(.*?)</td>", r) for r in re.findall(r"<tr><td>.*?</tr>", page)]
    cells = [dict(zip(head, r)) for r in rows]
    assert head == ["axis", "node", "status", "K_fc*", "sigma", "true (sim)", "error re truth", "excitation",
                    "verdict / error"]
    assert cells[0] == {"axis": "<a href='a/report.html'>a</a>", "node": "5", "status": "ok", "K_fc*": "0.1183 V",
                        "sigma": "0.0017 V", "true (sim)": "0.1157 V", "error re truth": "+2.25 %",
                        "excitation": "41.5 s", "verdict / error": "odd nonlinear"}
    assert cells[1]["axis"] == "gh" and cells[1]["K_fc*"] == "&ndash;" and cells[1]["verdict / error"] == \
        "no SDO answer from node 9"
    assert cells[2]["sigma"] == "&ndash;" and cells[2]["true (sim)"] == "&ndash;"
    assert "wall 63.2 s; longest axis' excitation 41.5 s (all axes 41.5 s in sequence); bus 2.25 s; " \
           f"wall / longest excitation {round(63.2 / 41.5, 3)}." in page


def test_bus_model_figures_from_the_drive_sims_line(tmp_path):
    log = tmp_path / "drive_sim.log"
    log.write_text("drive_sim: listening\nCAN bus model: 12345 frames, 1357911 bits at 500000 bit/s\n")
    m = mc._bus_model_figures(str(log), 500000)
    assert (m["frames"], m["bits"], m["bitrate"]) == (12345, 1357911, 500000)
    assert m["busy_s"] == round(1357911 / 500000, 3)
    log.write_text("drive_sim: listening\n")
    assert mc._bus_model_figures(str(log), 500000) is None
    assert mc._bus_model_figures(str(tmp_path / "none.log"), 500000) is None


def test_machine_summary_host_time_never_negative_and_budget_keys():
    axes = [{"name": "p", "time_budget_s": {"excitation": 20.0, "bus": 9.0, "drive_wait": 25.0}},
            {"name": "q", "time_budget_s": {"excitation": 12.0, "bus": 4.0, "drive_wait": 3.0}}]
    t = mc.machine_summary({"name": "m"}, axes, 22.0047, "t0")["time_budget_s"]["total"]
    # 22 - 9 (the longest SDO time) - 20 (p's wait, at most its excitation) < 0: 0
    assert t["host"] == 0.0 and t["bus"] == 9.0 and t["bus_sdo_wall"] == 13.0
    assert t["wall"] == 22.005 and t["wall_re_longest_excitation"] == 1.1       # (ms, 1e-3)
    assert t["measure_wall"] is None and t["measure_re_longest_excitation"] is None
    t = mc.machine_summary({"name": "m"}, [{"name": "r", "time_budget_s": None}], 5.0, "t0")["time_budget_s"]["total"]
    assert (t["excitation"], t["bus"], t["wall_re_longest_excitation"], t["bus_re_longest_excitation"]) == \
        (0.0, 0.0, None, None)


def test_sim_axis_args_name_each_axis_plant(tmp_path):
    from fftune.host.sim import DEFAULT_PLANT
    plant = tmp_path / "p.yaml"
    plant.write_text((open(DEFAULT_PLANT).read()))
    machine = {"file": str(tmp_path / "m.yaml"), "axes": [
        {"name": "u", "node_id": 3, "plant": None, "plant_overrides": {}},
        {"name": "v", "node_id": 11, "plant": str(plant), "plant_overrides": {"plant": {"coulomb": 7.5e-3}}}]}
    args = mc.sim_axis_args(machine, str(tmp_path))
    assert args[:2] == ["--axis", f"3:{DEFAULT_PLANT}"]
    assert args[2] == "--axis" and args[3] == f"11:{tmp_path / 'plant_v.yaml'}"
    assert yaml.safe_load((tmp_path / "plant_v.yaml").read_text())["plant"]["coulomb"] == 7.5e-3

