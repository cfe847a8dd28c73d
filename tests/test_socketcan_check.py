"""SocketCAN errors name the cause and the way: no SocketCAN in the kernel (-> the qemu
guest, docs/vm-testing.md), no such interface (-> how to make a vcan), not a CAN interface,
interface down (-> ip link set up); from the library function and from `fftune run` /
`fftune demo`."""
import errno
import types

import pytest

from fftune.host import socketcan_check as sc
from fftune.host.cli import main


def _net(tmp_path, name, kind, flags):
    d = tmp_path / name
    d.mkdir()
    (d / "type").write_text(f"{kind}\n")
    (d / "flags").write_text(f"{flags:#x}\n")


def _ok():
    return None


def _raise(code):
    def probe():
        raise OSError(code, "x")
    return probe


def test_each_cause_and_its_way(tmp_path):
    _net(tmp_path, "vcan0", 280, 0xC1)        # up (IFF_UP | IFF_RUNNING | IFF_NOARP)
    _net(tmp_path, "vcan1", 280, 0xC0)        # down
    _net(tmp_path, "eth0", 1, 0x1003)         # ethernet, up
    p = lambda ch, probe=_ok: sc.socketcan_problem(ch, sys_net=str(tmp_path), af_can_probe=probe)  # noqa: E731
    assert p("vcan0") is None
    assert p("vcan1") == "interface vcan1 is down: ip link set up vcan1 (as root)"
    assert p("eth0") == "eth0 is not a CAN interface (link type 1, CAN is 280)"
    missing = p("can7")
    assert missing.startswith("no such network interface 'can7'") and \
        "ip link add dev can7 type vcan" in missing and "docs/vm-testing.md" in missing
    nokernel = p("vcan0", _raise(errno.EAFNOSUPPORT))
    assert nokernel.startswith("no SocketCAN in this kernel") and "docs/vm-testing.md" in nokernel
    assert p("vcan0", _raise(errno.EPERM)).startswith("not allowed to open a raw CAN socket")
    assert p("../etc").startswith("no such network interface")
    assert p("").startswith("no interface named")


@pytest.fixture
def no_af_can(monkeypatch):
    def sock(*a, **k):
        raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
    monkeypatch.setattr(sc, "socket", types.SimpleNamespace(AF_CAN=29, SOCK_RAW=3, CAN_RAW=1, socket=sock))


@pytest.mark.parametrize("command", ["run", "demo"])
def test_entry_points_name_the_cause(no_af_can, tmp_path, capsys, command):
    rc = main([command, "-i", "socketcan", "-c", "vcan0", "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert err[0].startswith("fftune: error: ") and "no SocketCAN in this kernel" in err[0] \
        and "docs/vm-testing.md" in err[0]
    assert not (tmp_path / "o").exists()
