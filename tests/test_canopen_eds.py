"""The EDS generated from configs/od.yaml: python-canopen imports it, and every entry is
readable / writable on the running node with the declared type and access."""
import os
import struct
import subprocess
import sys

import canopen
import pytest
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes
from canopen.sdo import SdoAbortedError

from conftest import DRIVE_SIM_EDS, REPO

ODGEN = os.path.join(REPO, "firmware_sim", "tools", "odgen.py")
OD_YAML = os.path.join(REPO, "configs", "od.yaml")
DOC = os.path.join(REPO, "docs", "object-dictionary.md")

SIZES = {datatypes.BOOLEAN: 1, datatypes.INTEGER8: 1, datatypes.UNSIGNED8: 1,
         datatypes.INTEGER16: 2, datatypes.UNSIGNED16: 2, datatypes.INTEGER32: 4,
         datatypes.UNSIGNED32: 4, datatypes.REAL32: 4}


def _variables(od):
    for obj in od.values():
        if isinstance(obj, ODVariable):
            yield obj
        elif isinstance(obj, (ODRecord, ODArray)):
            yield from obj.values()


def _generate(tmp_path):
    out = tmp_path / "gen"
    subprocess.run([sys.executable, ODGEN, OD_YAML, str(out)], check=True)
    return out


def test_eds_in_the_build_is_what_od_yaml_generates(tmp_path):
    if not os.path.exists(DRIVE_SIM_EDS):
        pytest.skip(f"{DRIVE_SIM_EDS} not generated (run `make setup`)")
    out = _generate(tmp_path)
    for name in ("fftune_drive.eds", "od_table.c", "od_table.h", "od_params.h"):
        built = os.path.join(os.path.dirname(DRIVE_SIM_EDS), name)
        assert open(out / name).read() == open(built).read(), name


def test_packaged_eds_is_what_od_yaml_generates(tmp_path):
    """configs/fftune_drive.eds (package data the host reads) is current with od.yaml."""
    packaged = os.path.join(REPO, "configs", "fftune_drive.eds")
    assert open(_generate(tmp_path) / "fftune_drive.eds").read() == open(packaged).read(), \
        "configs/fftune_drive.eds is stale: make -C firmware_sim gen"


def test_object_dictionary_doc_table_is_generated_from_od_yaml(tmp_path):
    doc = tmp_path / "object-dictionary.md"
    doc.write_text(open(DOC).read())
    subprocess.run([sys.executable, ODGEN, OD_YAML, str(tmp_path / "gen"), "--doc", str(doc)],
                   check=True)
    assert doc.read_text() == open(DOC).read(), "docs/object-dictionary.md is stale: make -C firmware_sim canopen-doc"


def test_eds_imports_with_device_info_pdos_and_402_objects(tmp_path):
    od = canopen.import_od(str(_generate(tmp_path) / "fftune_drive.eds"), 1)
    assert od.device_information.vendor_number == 0x0FF7
    assert od.device_information.nr_of_RXPDO == 4 and od.device_information.nr_of_TXPDO == 4
    for index in (0x1000, 0x1001, 0x1017, 0x1018, 0x1400, 0x1600, 0x1800, 0x1A00,
                  0x6040, 0x6041, 0x6060, 0x6061, 0x6064, 0x606C, 0x607A, 0x60F4, 0x2002, 0x2021):
        assert index in od
    assert od[0x1800][1].default == 0x181                          # $NODEID resolved
    assert od[0x2002].data_type == datatypes.DOMAIN
    assert od["Controller"]["Coulomb feed-forward K_fc"].data_type == datatypes.REAL32
    assert od[0x6041].pdo_mappable and not od["Controller"]["Kp"].pdo_mappable


def test_drive_profile_eds_has_no_simulation_only_objects(tmp_path):
    """odgen --profile drive (issue 21, docs/porting.md): the EDS of a drive build lacks the
    simulation-only objects (0x2100, and a sim_only sub of any record), holds every other
    entry exactly as the simulation EDS does, passes the host's drive-profile check, and
    its C tables are the simulation build's (their sim rows are under CO_SIM_BUILD)."""
    import yaml
    from fftune.host.odmap import missing_profile_objects

    sim = _generate(tmp_path)
    drive = tmp_path / "drive"
    proc = subprocess.run([sys.executable, ODGEN, OD_YAML, str(drive), "--profile", "drive"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    od_sim = canopen.import_od(str(sim / "fftune_drive.eds"), 1)
    od_drive = canopen.import_od(str(drive / "fftune_drive.eds"), 1)
    sim_only = [o["index"] for o in yaml.safe_load(open(OD_YAML))["objects"] if o.get("sim_only")]
    assert 0x2100 in sim_only
    for index in sim_only:
        assert index in od_sim and index not in od_drive
    kept = {(v.index, v.subindex) for v in _variables(od_drive)}
    want = {(v.index, v.subindex) for v in _variables(od_sim) if v.index not in sim_only}
    assert kept == want and len(kept) > 150
    for v in _variables(od_drive):
        ref = od_sim[v.index] if isinstance(od_sim[v.index], ODVariable) else od_sim[v.index][v.subindex]
        assert (v.name, v.data_type, v.access_type, v.default) == (ref.name, ref.data_type, ref.access_type, ref.default)
    text = open(drive / "fftune_drive.eds").read()
    assert "0x2100" not in text.split("[ManufacturerObjects]")[1].split("[")[0]
    assert "Drive build" in text and "Simulation build" in open(sim / "fftune_drive.eds").read()
    assert missing_profile_objects(od_drive) == []
    for name in ("od_table.c", "od_table.h", "od_params.h"):
        assert open(drive / name).read() == open(sim / name).read(), name
    # a sim_only sub-index of a record goes too (sub 0 recounted), the record stays
    y = open(OD_YAML).read().replace(
        "{sub: 4, name: Plant input, type: REAL32, access: ro, param: MEAS_PLANT_INPUT, default: 0.0, unit: V}",
        "{sub: 4, name: Plant input, type: REAL32, access: ro, param: MEAS_PLANT_INPUT, default: 0.0, unit: V, sim_only: true}")
    assert "sim_only: true}" in y
    (tmp_path / "od.yaml").write_text(y)
    subprocess.run([sys.executable, ODGEN, str(tmp_path / "od.yaml"), str(tmp_path / "d2"), "--profile", "drive"],
                   check=True)
    od2 = canopen.import_od(str(tmp_path / "d2" / "fftune_drive.eds"), 1)
    assert 3 in od2[0x2030] and 4 not in od2[0x2030] and od2[0x2030][0].default == 3
    # the profile is checked: one line, exit 2
    proc = subprocess.run([sys.executable, ODGEN, OD_YAML, str(tmp_path / "x"), "--profile", "real"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "--profile real" in proc.stderr and proc.stderr.count("\n") == 1
    assert "Traceback" not in proc.stderr


def test_bad_od_yaml_gives_one_line_naming_the_entry(tmp_path):
    bad = tmp_path / "od.yaml"
    text = open(OD_YAML).read().replace('map: ["0x6041:0", "0x6061:0"]', 'map: ["0x2000:1"]')
    bad.write_text(text)
    proc = subprocess.run([sys.executable, ODGEN, str(bad), str(tmp_path / "gen")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "0x2000:1 is not a PDO-mappable object" in proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    assert not (tmp_path / "gen" / "od_table.c").exists()


def test_every_eds_entry_round_trips_on_the_running_node(co_node):
    net, node = co_node
    od = node.object_dictionary
    checked = {"read": 0, "write": 0, "ro": 0, "wo": 0}
    for var in _variables(od):
        ix, sub = var.index, var.subindex
        if var.data_type == datatypes.DOMAIN:
            continue                       # DOMAINs: test_canopen_sdo.py (table, recorder)
        if var.readable:
            raw = node.sdo.upload(ix, sub)
            if var.data_type in SIZES:
                assert len(raw) == SIZES[var.data_type], f"0x{ix:04X}:{sub} {var.name}"
            else:
                assert var.data_type == datatypes.VISIBLE_STRING
                assert raw.decode("ascii") == var.default
            if var.default is not None and not (0x6062 <= ix <= 0x60F4 and ix != 0x6060) \
                    and var.data_type in SIZES and ix not in (0x1001, 0x6041):
                fmt = var.STRUCT_TYPES[var.data_type].format
                value = struct.unpack(fmt, raw)[0]
                if ix < 0x2000 or ix >= 0x6000:  # communication / 402: EDS default = node value
                    assert value == var.default, f"0x{ix:04X}:{sub} {var.name}"
            checked["read"] += 1
        else:
            with pytest.raises(SdoAbortedError) as info:
                node.sdo.upload(ix, sub)
            assert info.value.code == 0x06010001
            checked["wo"] += 1
        if var.writable:
            if var.readable:
                value = raw
            else:
                value = (var.default or 0).to_bytes(SIZES[var.data_type], "little")
            node.sdo.download(ix, sub, value)
            if var.readable:
                assert node.sdo.upload(ix, sub) == value, f"0x{ix:04X}:{sub} {var.name}"
            checked["write"] += 1
        else:
            with pytest.raises(SdoAbortedError) as info:
                node.sdo.download(ix, sub, raw if var.readable else b"\0")
            assert info.value.code == 0x06010002, f"0x{ix:04X}:{sub} {var.name}"
            checked["ro"] += 1
    assert checked["read"] > 150 and checked["write"] > 90 and checked["ro"] > 40 and checked["wo"] == 1
