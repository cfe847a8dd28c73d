"""The feed-forward gains of issue 35 (K_fa 0x2000:9, K_ps 0x2000:10, K_pc 0x2000:11) attacked
over SDO with python-canopen as the peer, against drive_sim: NaN, +-inf, values beyond the
od.yaml range, wrong sizes, and writes while a run is active; each refusal is the abort
code of the cause and leaves the old value; the EDS describes them as od.yaml does."""
import math
import struct

import numpy as np
import pytest
import yaml
from canopen.objectdictionary import datatypes
from canopen.sdo import SdoAbortedError

from canopen_helpers import configure_sine_run, enable_402, start_long_run, wait_for
from fftune.host.odmap import DEFAULT_EDS, OD_YAML

SUBS = {9: "KFA", 10: "KPS", 11: "KPC"}
AB_INVALID, AB_HIGH, AB_LOW = 0x06090030, 0x06090031, 0x06090032
AB_SHORT, AB_LONG = 0x06070013, 0x06070012


def _abort_of(fn):
    with pytest.raises(SdoAbortedError) as info:
        fn()
    return info.value.code


def _f32(x):
    return struct.pack("<f", x)


def _od_entries():
    with open(OD_YAML, encoding="utf-8") as fh:
        od = yaml.safe_load(fh)
    ctl = next(o for o in od["objects"] if o["index"] == 0x2000)
    return {e["sub"]: e for e in ctl["sub"]}


def test_eds_lists_the_gains_as_od_yaml_does():
    import configparser

    import canopen
    od = canopen.import_od(DEFAULT_EDS, 1)
    eds = configparser.RawConfigParser()
    eds.optionxform = str
    eds.read(DEFAULT_EDS, encoding="utf-8")
    entries = _od_entries()
    ctl = od[0x2000]
    assert ctl[0].default == max(entries)               # highest sub-index: 11
    for sub, param in SUBS.items():
        e, var = entries[sub], ctl[sub]
        assert e["param"] == param
        assert var.name == e["name"] and var.data_type == datatypes.REAL32
        assert var.readable and var.writable
        assert var.default == e["default"] == 0.0 and var.unit == e["unit"] == "V"
        # (python-canopen 2.4 reads LowLimit / HighLimit of integer types only: the text)
        section = eds[f"2000sub{sub:X}"]
        assert (float(section["LowLimit"]), float(section["HighLimit"])) == (e["low"], e["high"]) == (-100.0, 100.0)
        # (a ";" starts an INI comment: the generator writes ",")
        assert section["PDOMapping"] == "0" and section["Description"] == e["doc"].replace(";", ",")


@pytest.mark.parametrize("sub", sorted(SUBS))
def test_gain_writes_refused_with_their_cause_and_the_old_value_kept(co_node, sub):
    net, node = co_node
    good = -0.37 + 0.01 * sub                      # unequal per gain
    node.sdo.download(0x2000, sub, _f32(good))
    assert node.sdo[0x2000][sub].raw == pytest.approx(good, abs=1e-7)
    for bad, code in ((math.nan, AB_INVALID), (math.inf, AB_INVALID), (-math.inf, AB_INVALID),
                      (100.5, AB_HIGH), (3e38, AB_HIGH), (-100.5, AB_LOW), (-3.4e38, AB_LOW)):
        assert _abort_of(lambda: node.sdo.download(0x2000, sub, _f32(bad))) == code, bad
    # a NaN with another payload (signalling, negative) is the same
    assert _abort_of(lambda: node.sdo.download(0x2000, sub, b"\x01\x00\x80\xff")) == AB_INVALID
    # the range ends are accepted and written back exactly
    for edge in (100.0, -100.0):
        node.sdo.download(0x2000, sub, _f32(edge))
        assert node.sdo.upload(0x2000, sub) == _f32(edge)
    node.sdo.download(0x2000, sub, _f32(good))
    # wrong sizes: 2 bytes (expedited), 8 bytes (segmented)
    assert _abort_of(lambda: node.sdo.download(0x2000, sub, b"\x00\x00")) == AB_SHORT
    assert _abort_of(lambda: node.sdo.download(0x2000, sub, _f32(1.0) * 2, force_segment=True)) == AB_LONG
    assert node.sdo[0x2000][sub].raw == pytest.approx(good, abs=1e-7)
    # the other two gains are untouched by all this
    for other in SUBS:
        if other != sub:
            assert node.sdo[0x2000][other].raw == 0.0


@pytest.mark.drive_sim_args("--realtime")
def test_gains_during_a_run_accepted_and_bad_ones_refused_without_a_fault(co_node):
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    node.sdo[0x6060].raw = -1
    assert enable_402(node) & 0x6F == 0x27
    node.sdo["Controller"]["Coulomb feed-forward K_fc"].raw = 0.1
    start_long_run(node)
    assert wait_for(lambda: node.sdo["Run control"]["State"].raw in (1, 2), 2.0)
    for sub in SUBS:
        node.sdo[0x2000][sub].raw = 0.02 * sub                      # settable while running
        assert node.sdo[0x2000][sub].raw == pytest.approx(0.02 * sub, abs=1e-7)
        for bad in (math.nan, math.inf, 1e30):
            assert _abort_of(lambda: node.sdo.download(0x2000, sub, _f32(bad))) in (AB_INVALID, AB_HIGH)
        assert node.sdo[0x2000][sub].raw == pytest.approx(0.02 * sub, abs=1e-7)
    # still running, no fault, a finite plant input
    assert node.sdo["Run control"]["State"].raw in (1, 2)
    assert node.sdo[0x6041].raw & 0x4F != 0x08
    assert np.isfinite(node.sdo["Measurements"]["Plant input"].raw)
    node.sdo["Run control"]["Command"].raw = 2          # abort the run
    assert wait_for(lambda: node.sdo["Run control"]["State"].raw not in (1, 2), 2.0)


def test_position_gains_move_the_recorded_plant_input_as_the_formula(co_node):
    """A short sine run with Kp = Kd = K_v = 0 (the feed-forward alone): with every Coulomb
    term written over SDO the recorded plant input follows
    sgn(v_r) (K_fc + K_ps sin th_r + K_pc cos th_r) + K_fa |sgn| at the recorded reference,
    within the level table's bound."""
    net, node = co_node
    node.nmt.state = "OPERATIONAL"
    c = node.sdo["Controller"]
    c["Kp"].raw = 0.0
    c["Kd"].raw = 0.0
    kfc, kfa, kps, kpc = 0.3, -0.07, 0.11, -0.05
    for name, v in (("Coulomb feed-forward K_fc", kfc), ("Viscous feed-forward K_v", 0.0)):
        c[name].raw = v
    for sub, v in ((9, kfa), (10, kps), (11, kpc)):
        node.sdo[0x2000][sub].raw = v
    node.sdo[0x6060].raw = -1
    assert enable_402(node) & 0x6F == 0x27
    configure_sine_run(node, period=512, settle=0, record=1, amplitude=4.0, signals=0x03)
    node.sdo["Run control"]["Command"].raw = 1
    assert wait_for(lambda: node.sdo["Run control"]["State"].raw not in (1, 2), 20.0)
    data = np.frombuffer(node.sdo.upload(0x2021, 0), "<f4").reshape(-1, 2).astype(float)
    ref, u = data[:, 0], data[:, 1]
    k = np.arange(ref.size)
    v = np.cos(2 * np.pi * k / 512)                      # the sine's velocity sign (cycles 1)
    moving = np.abs(v) > 0.05
    sg = np.sign(v)
    expect = sg * (kfc + kps * np.sin(ref) + kpc * np.cos(ref)) + kfa * np.abs(sg)
    tol = 0.5 * (2 * np.pi / 128) ** 2 * math.hypot(kps, kpc) + 1e-5
    assert moving.sum() > 400
    assert np.max(np.abs(u[moving] - expect[moving])) <= tol
