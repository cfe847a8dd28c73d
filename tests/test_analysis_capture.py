"""Capture files: round trip, atomic no-clobber writes, directory assembly, exports; io loaders."""
import json
import os

import numpy as np
import pytest
import scipy.io

from fftune.analysis import capture
from fftune.analysis.errors import FftuneError, InputError
from fftune.analysis.io import load_lines, load_signals

N, T, P = 64, 1, 3


def meta(**kw):
    m = {"fs_hz": 1000.0, "n_period": N, "settle_periods": T, "record_periods": P,
         "experiment": "multisine", "level_index": 0, "realization": 0,
         "parameters": {"exc_amplitude": 0.5, "ms_seed": 7}, "firmware_version": "fw 1.2.3",
         "eds_identity": json.dumps({"vendor_id": 1}), "started_at": "2026-01-01T00:00:00+00:00",
         "metadata": {"operator": "test", "nested": [1, 2]}}
    m.update(kw)
    return m


def signals(seed=0):
    rng = np.random.default_rng(seed)
    return {name: rng.standard_normal((T + P) * N) for name in capture.STANDARD_SIGNALS}


def test_round_trip(tmp_path):
    sig = signals()
    path = capture.write_run(tmp_path / "run.h5", sig, meta())
    run = capture.read_run(path)
    assert set(run.signals) == set(capture.STANDARD_SIGNALS)
    for name, values in sig.items():
        assert run.signals[name].dtype == np.float32
        np.testing.assert_array_equal(run.signals[name], values.astype(np.float32))
    assert run.meta["fs_hz"] == 1000.0 and run.meta["n_period"] == N
    assert run.meta["parameters"] == {"exc_amplitude": 0.5, "ms_seed": 7}
    assert run.meta["metadata"]["nested"] == [1, 2]
    assert run.meta["firmware_version"] == "fw 1.2.3"
    assert run.meta["finished_at"].startswith("20")              # defaulted to now, ISO
    assert run.periods("reference").shape == (T + P, N)
    assert [p.name for p in tmp_path.iterdir()] == ["run.h5"]     # no temp file left


def test_refuses_to_overwrite_and_leaves_nothing_half_written(tmp_path):
    path = tmp_path / "run.h5"
    capture.write_run(path, signals(0), meta())
    before = path.read_bytes()
    with pytest.raises(FileExistsError):
        capture.write_run(path, signals(1), meta())
    with pytest.raises(FftuneError, match="refusing to overwrite"):
        capture.write_run(path, signals(1), meta())
    assert path.read_bytes() == before
    bad = signals()
    bad["error"] = bad["error"][:-1]
    with pytest.raises(InputError, match="signal error has shape"):
        capture.write_run(tmp_path / "bad.h5", bad, meta())
    nan = signals()
    nan["reference"][5] = np.nan
    with pytest.raises(InputError, match="NaN"):
        capture.write_run(tmp_path / "nan.h5", nan, meta())
    with pytest.raises(InputError, match="missing metadata fs_hz"):
        capture.write_run(tmp_path / "m.h5", signals(), {k: v for k, v in meta().items()
                                                          if k != "fs_hz"})
    with pytest.raises(InputError, match="started_at 'yesterday' is not an ISO 8601"):
        capture.write_run(tmp_path / "m.h5", signals(), meta(started_at="yesterday"))
    with pytest.raises(InputError, match="unknown metadata"):
        capture.write_run(tmp_path / "m.h5", signals(), meta(colour="red"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.h5"]


def test_read_rejects_foreign_files(tmp_path):
    import h5py
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["x"] = np.zeros(3)
    with pytest.raises(InputError, match="not an fftune capture"):
        capture.read_run(tmp_path / "other.h5")
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(InputError, match="not an HDF5"):
        capture.read_run(tmp_path / "text.h5")


def test_load_experiment_assembles_realizations(tmp_path):
    sigs = [signals(m) for m in range(3)]
    for m in (2, 0, 1):
        capture.write_run(tmp_path / f"ms-M{m}.h5", sigs[m], meta(realization=m))
    exp = capture.load_experiment(tmp_path)
    assert exp.signals["motor_angle"].shape == (3, T + P, N)
    for m in range(3):
        np.testing.assert_array_equal(exp.signals["motor_angle"][m].reshape(-1),
                                      sigs[m]["motor_angle"].astype(np.float32))
    assert exp.settle_periods == T and exp.record_periods == P and exp.fs_hz == 1000.0
    # inconsistent layout is named
    capture.write_run(tmp_path / "ms-M3.h5", signals(3), meta(realization=3, fs_hz=500.0))
    with pytest.raises(InputError, match="ms-M3.h5: fs_hz"):
        capture.load_experiment(tmp_path)
    os.unlink(tmp_path / "ms-M3.h5")
    capture.write_run(tmp_path / "ms-M1b.h5", signals(4), meta(realization=1))
    with pytest.raises(InputError, match="realization indices"):
        capture.load_experiment(tmp_path)
    os.unlink(tmp_path / "ms-M1b.h5")
    capture.write_run(tmp_path / "lv1.h5", signals(5), meta(level_index=1))
    with pytest.raises(InputError, match="several levels"):
        capture.load_experiment(tmp_path)
    assert capture.load_experiment(tmp_path, level_index=1).signals["error"].shape == (1, T + P, N)


def test_exports_read_back(tmp_path):
    sig = signals()
    path = capture.write_run(tmp_path / "run.h5", sig, meta())
    mat = capture.export_mat(path, tmp_path / "run.mat")
    content = scipy.io.loadmat(mat, simplify_cells=True)["run"]
    np.testing.assert_array_equal(content["signals"]["plant_input"],
                                  sig["plant_input"].astype(np.float32))
    assert content["fs_hz"] == 1000.0
    from_mat = load_signals(mat)                  # `fftune analyze` reads the export back
    assert from_mat.fs_hz == 1000.0 and from_mat.layout["n_period"] == N
    np.testing.assert_array_equal(from_mat.signals["error"], sig["error"].astype(np.float32))
    csv_path = capture.export_csv(path, tmp_path / "run.csv")
    loaded = load_signals(csv_path)
    assert loaded.fs_hz == 1000.0 and loaded.layout["n_period"] == N
    np.testing.assert_allclose(loaded.signals["load_angle"], sig["load_angle"], rtol=1e-6)
    with pytest.raises(FileExistsError):
        capture.export_csv(path, csv_path)
    via_io = load_signals(path)
    assert via_io.layout == {"n_period": N, "settle_periods": T, "record_periods": P,
                             "realizations": 1}


def test_io_loaders_and_their_errors(tmp_path):
    good = tmp_path / "d.csv"
    good.write_text("# comment\nu,y\n1,2\n3,4\n")
    assert load_signals(good).signals["y"].tolist() == [2.0, 4.0]
    bad = tmp_path / "bad.csv"
    bad.write_text("u,y\n1,2\n3,abc\n")
    with pytest.raises(InputError, match=r"bad.csv line 3, column 'y': 'abc' is not a number"):
        load_signals(bad)
    short = tmp_path / "short.csv"
    short.write_text("u,y\n1,2\n3\n")
    with pytest.raises(InputError, match="line 3: 1 fields"):
        load_signals(short)
    nan = tmp_path / "nan.csv"
    nan.write_text("u,y\n1,2\n3,nan\n")
    with pytest.raises(InputError, match="line 3, column 'y': NaN"):
        load_signals(nan)
    noheader = tmp_path / "nohead.csv"
    noheader.write_text("1,2\n3,4\n")
    with pytest.raises(InputError, match="header"):
        load_signals(noheader)
    np.savez(tmp_path / "d.npz", u=np.ones((2, 3)), y=np.zeros(6), fs=np.float64(50.0))
    z = load_signals(tmp_path / "d.npz")
    assert z.fs_hz == 50.0 and z.signals["u"].shape == (6,)
    scipy.io.savemat(tmp_path / "d.mat", {"u": np.ones((6, 1)), "y": np.arange(6.0), "fs": 20.0})
    m = load_signals(tmp_path / "d.mat")
    assert m.fs_hz == 20.0 and m.signals["y"].tolist() == list(range(6))
    with pytest.raises(InputError, match="unknown file type"):
        load_signals(good.rename(tmp_path / "d.xls"))
    with pytest.raises(InputError, match="no such file"):
        load_signals(tmp_path / "missing.csv")
    lines = tmp_path / "lines.txt"
    lines.write_text("# excited\n3, 5 7\n9\n")
    assert load_lines(lines).tolist() == [3, 5, 7, 9]
    lines.write_text("3\nfive\n")
    with pytest.raises(InputError, match="line 2: 'five'"):
        load_lines(lines)
