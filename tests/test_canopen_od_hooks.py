"""Write hooks declared per object in configs/od.yaml (issue 10, structure): odgen puts a
pointer to co_hook_NAME into the generated table, the CANopen module owning the side effect
defines it, and nothing in co_od.c dispatches on an index any more."""
import os
import re
import shutil
import subprocess
import sys

import pytest
import yaml

from conftest import REPO

ODGEN = os.path.join(REPO, "firmware_sim", "tools", "odgen.py")
OD_YAML = os.path.join(REPO, "configs", "od.yaml")
FW = os.path.join(REPO, "firmware_sim")


def _odgen(yaml_path, out):
    return subprocess.run([sys.executable, ODGEN, str(yaml_path), str(out)],
                          capture_output=True, text=True)


def _variant(tmp_path, old, new):
    text = open(OD_YAML).read()
    assert old in text, old
    path = tmp_path / "od.yaml"
    path.write_text(text.replace(old, new))
    return path


def test_every_side_effect_is_a_hook_declared_in_od_yaml(tmp_path):
    proc = _odgen(OD_YAML, tmp_path / "gen")
    assert proc.returncode == 0, proc.stderr
    table = (tmp_path / "gen" / "od_table.c").read_text()
    od = yaml.safe_load(open(OD_YAML))
    declared = {}
    for obj in od["objects"]:
        for s in obj.get("sub", [obj]):
            if "hook" in s:
                declared[(obj["index"], s.get("sub", 0))] = s["hook"]
    assert declared[(0x1016, 1)] == "hb_consumer" and declared[(0x1017, 0)] == "hb_producer"
    assert declared[(0x6040, 0)] == "controlword" and declared[(0x2010, 1)] == "run_command"
    rows = re.findall(r"\{0x([0-9A-F]{4}), (\d+), .*?, (NULL|&co_hook_\w+)\}, /\*", table)
    assert rows
    for ix, sub, hook in rows:
        ix, sub = int(ix, 16), int(sub)
        want = declared.get((ix, sub))
        if 0x1400 <= ix <= 0x1BFF:                    # odgen adds it to PDO entries
            comm_sub0 = sub == 0 and not ix & 0x0200    # "highest sub-index": const
            want = None if comm_sub0 else "pdo"
        assert hook == (f"&co_hook_{want}" if want else "NULL"), (hex(ix), sub, hook)
    # the dispatcher itself knows no object index
    src = open(os.path.join(FW, "canopen", "co_od.c")).read()
    assert not re.search(r"0x(1016|1017|14|16|18|1A|6040|6060|607A)", src, re.IGNORECASE)


@pytest.mark.parametrize("old, new, message", [
    ("ram: hb_producer_ms,\n     hook: hb_producer}", "ram: hb_producer_ms,\n     hook: Bad-Name}",
     "0x1017:0: hook must be a lower-case C identifier"),
    ("{index: 0x1000, name: Device type, type: UNSIGNED32, access: ro, default: 0x00020192}",
     "{index: 0x1000, name: Device type, type: UNSIGNED32, access: ro, default: 0x00020192, hook: x}",
     "0x1000:0: write hook 'x' on a read-only object"),
    ("access: rw, domain: table,", "access: rw,",
     "0x2002:0: DOMAIN object needs `domain:`"),
])
def test_bad_hook_declarations_give_one_line(tmp_path, old, new, message):
    proc = _odgen(_variant(tmp_path, old, new), tmp_path / "gen")
    assert proc.returncode == 2
    assert message in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler (cc) to link the table")
def test_a_hook_no_module_implements_fails_the_link(tmp_path):
    """A name in od.yaml without a co_hook_NAME definition cannot slip through: the node
    (canopen/*.c + the drive test double) does not link."""
    gen = tmp_path / "gen"
    path = _variant(tmp_path, "ram: target_position,\n     hook: target_position}",
                    "ram: target_position,\n     hook: nobody_implements_this}")
    assert _odgen(path, gen).returncode == 0
    double = tmp_path / "double"
    double.mkdir()
    shutil.copy(os.path.join(FW, "core", "drv.h"), double)
    shutil.copy(os.path.join(FW, "canopen", "tests", "drv_state.h"), double)
    srcs = sorted(os.path.join(FW, "canopen", f) for f in os.listdir(os.path.join(FW, "canopen"))
                  if f.startswith("co_") and f.endswith(".c"))
    srcs += [os.path.join(FW, "canopen", "tests", f) for f in ("drv_double.c", "test_co.c")]
    cmd = ["cc", "-std=c11", "-DCO_SIM_BUILD", f"-I{double}", f"-I{FW}/canopen",
           f"-I{FW}/canopen/tests", f"-I{gen}", *srcs, str(gen / "od_table.c"), "-lm",
           "-o", str(tmp_path / "co_test")]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode != 0
    assert "co_hook_nobody_implements_this" in proc.stderr
