"""`fftune fleet` outputs a person opens (CSV beside Parquet, report.html, drift plots that
fit one and many analyses, names from the results) and its robustness: a damaged
results.yaml axis block is a row with its reason, every row passes one type check, the
--scheduler connect and handshake are bounded with one error line each."""
import datetime
import shutil
import socket
import threading

import pytest
import yaml

from fftune.host import fleet
from fftune.host.cli import main
from fftune.host.pipeline import run_pipeline
from host_fixtures import FakeDriveForTests
from test_host_experiments import _cfg


def _small_cfg():
    # one tune only (a few experiments): the fleet's names and rows, not the analysis, are
    # under test here
    cfg = _cfg()
    cfg["detect"]["enabled"] = cfg["quantify"]["enabled"] = False
    cfg["tune"]["sweep"]["points"] = 0
    cfg["tune"]["viscous"]["enabled"] = False
    return cfg


@pytest.fixture(scope="module")
def one_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet-out")
    d = FakeDriveForTests(fc_volt=0.3, fv_volt=0.02, noise_std=1e-5)
    d.enable()
    run_pipeline(d, _small_cfg(), str(root / "out" / "demo"), log=lambda s: None, figures=False)
    return root


DAMAGED = {
    "machine_5": ({"machine": 5, "name": "x"}, "axis.machine"),
    "node_abc": ({"machine": "m", "name": "x", "node_id": "abc"}, "axis.node_id"),
    "name_list": ({"machine": "m", "name": [1, 2]}, "axis.name"),
    "node_23_digits": ({"machine": "m", "name": "x", "node_id": 12345678901234567890123}, "axis.node_id"),
    "axis_text": ("just text", "key 'axis'"),
}


def test_damaged_results_axis_blocks_are_rows_with_their_reason(one_run, tmp_path, capsys):
    src = one_run / "out" / "demo"
    for name, (axis, _) in DAMAGED.items():
        dst = tmp_path / "fleet" / name
        shutil.copytree(src, dst)
        res = yaml.safe_load((dst / "results.yaml").read_text())
        res["axis"] = axis
        (dst / "results.yaml").write_text(yaml.safe_dump(res))
    # and a results.yaml that is no mapping, one that is an alias bomb
    shutil.copytree(src, tmp_path / "fleet" / "listed")
    (tmp_path / "fleet" / "listed" / "results.yaml").write_text("- 1\n- 2\n")
    shutil.copytree(src, tmp_path / "fleet" / "bomb")
    bomb = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{c}: &{c} [*{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}, *{p}]\n"
        for p, c in zip("abcdefg", "bcdefgh"))
    (tmp_path / "fleet" / "bomb" / "results.yaml").write_text(bomb)
    out = tmp_path / "o"
    assert main(["fleet", str(tmp_path / "fleet"), "--out", str(out), "--scheduler", "sync"]) == 0
    rows = fleet.read_table(str(out / "fleet.csv"))
    by = {r["source"].split("/")[-2]: r for r in rows}
    assert len(rows) == len(DAMAGED) + 2
    for name, (_, key) in DAMAGED.items():
        assert by[name]["status"] == "error" and key in by[name]["reason"], (name, by[name]["reason"])
    assert "expected a mapping at the top level" in by["listed"]["reason"]
    assert "alias bomb" in by["bomb"]["reason"]
    # the folder names stand in for the names the damaged block could not give
    assert by["machine_5"]["machine"] == "fleet" and by["machine_5"]["axis"] == "machine_5"
    assert (out / "fleet.parquet").exists() and (out / "report.html").exists()


def test_every_row_passes_one_type_check():
    row = fleet._empty_row("/a/captures", "captures")
    row.update(status="ok", machine="m", axis="x", node_id=10 ** 22, k_fc_star="0.3",
               bla_rms_levels=[1.0, "x"], k_fc_converged=True, runs=4)
    out = fleet.checked_row(row)
    assert out["status"] == "error" and out["node_id"] is None and out["k_fc_star"] is None
    assert out["bla_rms_levels"] is None and out["runs"] == 4 and out["k_fc_converged"] is True
    assert "column node_id" in out["reason"] and "column k_fc_star" in out["reason"] \
        and "column bla_rms_levels" in out["reason"]
    fleet.arrow_table([out])          # the table takes it
    ok = fleet._empty_row("/b/captures", "captures")
    ok.update(status="ok", node_id=3, k_fc_star=0.3)
    assert fleet.checked_row(ok)["status"] == "ok"


def test_outputs_for_one_analysis_named_from_the_results(one_run, tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["fleet", str(one_run / "out"), "--out", str(out), "--scheduler", "sync"]) == 0
    printed = capsys.readouterr().out
    assert "fleet.parquet" in printed and "fleet.csv" in printed and "report.html" in printed
    pq, csv = fleet.read_table(str(out / "fleet.parquet")), fleet.read_table(str(out / "fleet.csv"))
    assert [r["k_fc_star"] for r in pq] == [r["k_fc_star"] for r in csv] and len(pq) == 1
    page = (out / "report.html").read_text()
    # named after the drive of its results (device name, node), not the folders "out / demo"
    assert "FakeDriveForTests, node 1" in page and "<img src='drift_out_demo.png'" in page
    assert "out / demo" not in page
    rows = fleet.run_graph(fleet.discover([str(one_run / "out")])[0], scheduler="sync")
    fig = fleet.drift_figure(rows, "out", "demo")
    ax1, ax2 = fig.axes[:2]
    # the time axis fits one analysis: a day around it, not years
    lo, hi = ax2.get_xlim()
    assert 0.5 <= hi - lo <= 2.0                     # days (matplotlib date numbers)
    truth = [ln for ln in ax1.get_lines() if ln.get_label().startswith("true Coulomb")]
    assert truth and truth[0].get_marker() == "x" and truth[0].get_ydata()[0] == rows[0]["k_fc_true"]
    assert "FakeDriveForTests, node 1" in ax1.get_title() and "(1 analysis)" in ax1.get_title()


def test_drift_axis_spans_many_dates():
    base = datetime.datetime(2026, 1, 1)
    rs = []
    for i, days in enumerate((0, 30, 95)):
        r = fleet._empty_row(f"/f/{i}/captures", "captures")
        r.update(status="ok", machine="m", axis="x", date=(base + datetime.timedelta(days=days)).isoformat(),
                 k_fc_star=0.3 + 0.01 * i, k_fc_sigma=0.002, ratio_at_zero=0.04, ratio_at_k_fc_star=0.001 * (i + 1))
        rs.append(r)
    fig = fleet.drift_figure(rs, "m", "x")
    lo, hi = fig.axes[1].get_xlim()
    assert 95 < hi - lo < 95 * 1.3
    assert not [ln for ln in fig.axes[0].get_lines() if ln.get_label().startswith("true")]


def test_batches_cover_every_item_in_order():
    items = [("captures", f"/d{i}") for i in range(11)]
    b = fleet.batches(items, 2)
    assert [it for x in b for it in x] == items and len(b) == 4
    assert fleet.batches(items[:3], 8) == [[it] for it in items[:3]]
    assert fleet.batches([], 2) == [[]] or fleet.batches([], 2) == []


class _Server:
    """A TCP server on a free loopback port that accepts and sends ``greeting`` (None:
    nothing, a silent port)."""

    def __init__(self, greeting):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(4)
        self.greeting, self.conns = greeting, []
        self.port = self.sock.getsockname()[1]
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                c, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(c)
            if self.greeting:
                c.sendall(self.greeting)

    def close(self):
        self.sock.close()
        for c in self.conns:
            c.close()


@pytest.mark.parametrize("greeting, expected", [
    (None, "connected, but no Dask handshake within 0.5 s"),
    (b"HTTP/1.1 400 Bad Request\r\n\r\n", "are no Dask handshake (not a Dask scheduler)"),
    (b"", None),
])
def test_scheduler_connect_and_handshake_are_bounded(one_run, tmp_path, capsys, monkeypatch, greeting, expected):
    monkeypatch.setattr(fleet, "CONNECT_TIMEOUT_S", 0.5)
    monkeypatch.setattr(fleet.probe_scheduler, "__defaults__", (0.5,))
    monkeypatch.setattr(fleet._distributed_client, "__defaults__", (0.5,))
    if greeting == b"":
        # a closed port: refused at once
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        s.close()
        srv, expected = None, "cannot connect"
    else:
        srv = _Server(greeting)
        port = srv.port
    try:
        rc = main(["fleet", str(one_run / "out"), "--out", str(tmp_path / "o"),
                   "--scheduler", f"tcp://127.0.0.1:{port}"])
    finally:
        if srv:
            srv.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith(f"fftune: error: --scheduler tcp://127.0.0.1:{port}: ")
    assert expected in err[0], err
    assert not any((tmp_path / "o").glob("fleet.*"))


@pytest.mark.parametrize("address", ["tcp://", "tcp://host", "tcp://:8786", "tcp://h:99999", "tcp://h:1/x"])
def test_scheduler_address_is_checked_before_anything(one_run, tmp_path, capsys, address):
    rc = main(["fleet", str(one_run / "out"), "--out", str(tmp_path / "o"), "--scheduler", address])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"fftune: error: --scheduler {address}: expected tcp://HOST:PORT (port 1..65535)"]
    assert not (tmp_path / "o").exists()
