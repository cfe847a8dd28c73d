"""report.html of `fftune track` / `demo-track`: the gains left on the drive first, a note on
every update of K_fc larger than 2 sigma (and none below), the K_fc path over the
tracking-error panel, results.yaml collapsed."""
import pytest

from fftune.analysis.plots import legend_outside_data
from fftune.host import track_report as tr


def _rows():
    # (K_fc the task ran with, estimate, sigma, K_fc set after it, rms error, truth)
    spec = [(0.2, 0.17, 0.01, 0.17, 0.09, 0.18),     # -0.03 = 3 sigma: noted
            (0.17, 0.1805, 0.01, 0.1805, 0.02, 0.18),  # +0.0105 = 1.05 sigma: not
            (0.1805, 0.18, 0.0001, 0.1805, 0.01, 0.18),  # no change
            (0.1805, None, None, 0.25, None, 0.18),    # no estimate: not judged
            (0.25, 0.181, 0.004, 0.1795, 0.012, 0.18)]  # -0.0705 = 17.6 sigma (rollback)
    rows = []
    for i, (k, est, sig, nxt, err, truth) in enumerate(spec):
        rows.append({"task": i, "t_s": 1.5 * (i + 1), "k_fc": k, "k_fc_estimate": est,
                     "k_fc_sigma": sig, "k_fc_next": nxt, "k_v": 0.01, "rms_error": err,
                     "action": "rollback" if i == 4 else "update", "k_fc_true": truth})
    return rows


def _results(rows):
    return {"track": rows, "track_summary": {
        "tasks": len(rows), "task_s": 1.5, "k_fc_final": 0.1795, "k_v_final": 0.01, "stop": None,
        "k_fc_true_final": 0.18, "check": None,
        "bus": {"bits_per_task_max": 5000, "task_traffic_load": 0.0033, "bitrate": 1000000}}}


def test_large_updates_are_those_over_two_sigma():
    big = tr.large_updates(_rows())
    assert [u["task"] for u in big] == [0, 4]
    assert big[0]["sigmas"] == pytest.approx(3.0) and big[0]["step_rel"] == pytest.approx(-0.15)
    assert big[0]["off_truth_rel"] == pytest.approx(0.17 / 0.18 - 1)
    assert big[1]["sigmas"] == pytest.approx(0.0705 / 0.004) and big[1]["action"] == "rollback"
    assert [u["task"] for u in tr.large_updates(_rows(), n_sigma=1.0)] == [0, 1, 4]


def test_report_page(tmp_path):
    rows = _rows()
    path = tr.write_track_report(str(tmp_path), _results(rows), {"drive": {"node_id": 7}, "_source": "t.yaml"})
    text = open(path).read()
    i_res, i_notes = text.index("<h2>On the drive</h2>"), text.index("Updates larger than 2 sigma (2)")
    assert i_res < i_notes < text.index("<details><summary>All results (results.yaml)</summary>")
    assert "K_fc = 0.1795 V (simulated truth 0.18 V) on object 0x2000:04 of node 7" in text
    assert "task 0 (t 1.5 s): K_fc moved from 0.2 V to 0.17 V (-15.0 %), 3.0 sigma" in text
    assert "task 1 (" not in text
    assert "0.09 / 0.012 rad" in text
    assert (tmp_path / "track_path.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_track_figure_has_the_error_panel_and_legends_outside():
    fig = tr.track_figure(_rows())
    a1, a2 = fig.axes[:2]
    assert list(a2.get_lines()[0].get_ydata()[:2]) == [0.09, 0.02]
    circled = [ln for ln in a1.get_lines() if ln.get_label().startswith("update >")]
    assert list(circled[0].get_xdata()) == [1.5, 7.5]
    assert legend_outside_data(fig) == []
