"""A drive without the fftune objects (a generic CiA 402 drive): one `fftune: error:` line
naming the missing objects and pointing to docs/drive-profile.md, before any experiment."""
import re
import subprocess
import sys
from pathlib import Path

import canopen
import yaml
import pytest

from conftest import drive_sim_missing_reason
from fftune.analysis.errors import FftuneError
from fftune.host.drive import BusOptions, DriveClient
from fftune.host.odmap import DEFAULT_EDS, missing_profile_objects, profile_objects

REPO = Path(__file__).resolve().parents[1]


def generic_eds(tmp_path, drop=re.compile(r"^2[0-9A-F]{3}")):
    """The fftune EDS without the sections ``drop`` matches: with the default, every
    manufacturer object goes and what is left is a generic CiA 301 + CiA 402 drive."""
    out, skip = [], False
    for line in Path(DEFAULT_EDS).read_text().splitlines():
        m = re.match(r"^\[(\w+)\]", line)
        if m:
            skip = bool(drop.match(m.group(1)))
        if not skip:
            out.append(line)
    text = "\n".join(out) + "\n"
    # the [ManufacturerObjects] list must only name sections that exist
    listed = re.search(r"\[ManufacturerObjects\]\n(.*?)\n\n", text, re.S)
    if listed:
        kept = [ln.split("=", 1)[1] for ln in listed.group(1).splitlines()
                if re.match(r"^\d+=", ln) and f"[{ln.split('=', 1)[1][2:].upper()}]" in text]
        body = f"SupportedObjects={len(kept)}\n" + "".join(f"{i}={v}\n" for i, v in enumerate(kept, 1))
        text = text.replace(listed.group(0), f"[ManufacturerObjects]\n{body}\n")
    path = tmp_path / "generic_402.eds"
    path.write_text(text)
    return path


def test_the_fftune_eds_has_every_profile_object():
    assert missing_profile_objects(canopen.import_od(DEFAULT_EDS)) == []


def test_generic_402_eds_is_refused_naming_the_missing_objects(tmp_path):
    eds = generic_eds(tmp_path)
    od = canopen.import_od(str(eds))
    assert 0x6041 in od and 0x2000 not in od          # a CiA 402 drive, no fftune objects
    with pytest.raises(FftuneError) as err:
        DriveClient(BusOptions(eds=str(eds)))
    msg = str(err.value)
    assert "\n" not in msg
    for name in ("0x2000 Controller", "0x2001 Excitation", "0x2010 Run control",
                 "0x2021 Recorder data", "docs/drive-profile.md"):
        assert name in msg
    assert "0x2100" not in msg                         # simulation-only objects are optional


def test_one_missing_sub_index_is_named(tmp_path):
    eds = generic_eds(tmp_path, drop=re.compile(r"^(2021|2010sub6)$"))
    msg = ", ".join(missing_profile_objects(canopen.import_od(str(eds))))
    assert msg == "0x2010:6 Run control.Run length, 0x2021 Recorder data"


@pytest.mark.skipif(drive_sim_missing_reason() is not None, reason=drive_sim_missing_reason() or "")
def test_cli_against_a_running_drive_with_a_generic_eds(tmp_path, drive_sim):
    """Before the check this ended in a KeyError traceback once the host addressed 0x2000."""
    eds = generic_eds(tmp_path)
    bus = (["-i", "socketcand", "--host", drive_sim.host, "--port", str(drive_sim.port)]
           if drive_sim.transport == "socketcand" else ["-i", "socketcan", "-c", drive_sim.channel])
    proc = subprocess.run([sys.executable, "-m", "fftune.host.cli", "detect", "--no-progress",
                           "--no-figures", "--out", str(tmp_path / "out"), "--eds", str(eds),
                           *bus], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fftune: error: EDS ")
    assert "0x2000 Controller" in lines[0] and "docs/drive-profile.md" in lines[0]
    assert not (tmp_path / "out").exists(), "a refused drive must leave nothing behind"


def test_profile_doc_lists_every_object():
    doc = (REPO / "docs" / "drive-profile.md").read_text()
    for index, sub, name in profile_objects():
        key = f"0x{index:04X}" if sub is None else f"0x{index:04X}:{sub}"
        assert key in doc, f"docs/drive-profile.md does not list {key} ({name})"


def test_od_yaml_is_parsed_once_per_version_and_a_missing_file_is_one_line(tmp_path):
    # every command reads od.yaml for its parameter map and the drive's limits (eleven
    # limits in a tune's preflight): one parse per process and version of the file
    import os
    import shutil

    from fftune.host import odmap

    copy = tmp_path / "od.yaml"
    shutil.copy(odmap.OD_YAML, copy)
    first = odmap.load_od(copy)
    misses = odmap._parsed.cache_info().misses
    assert odmap.load_od(copy) is first and odmap._parsed.cache_info().misses == misses
    assert first == yaml.safe_load(open(odmap.OD_YAML, encoding="utf-8"))   # libyaml: the same
    text = copy.read_text().replace("name: Controller", "name: Controller changed", 1)
    copy.write_text(text)
    st = os.stat(copy)
    os.utime(copy, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    second = odmap.load_od(copy)
    assert second is not first and odmap._parsed.cache_info().misses == misses + 1
    assert "Controller changed" in [o["name"] for o in second["objects"]]
    with pytest.raises(FftuneError, match=r"nope\.yaml: cannot read the object dictionary source"):
        odmap.load_od(tmp_path / "nope.yaml")
