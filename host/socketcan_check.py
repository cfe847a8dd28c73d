"""Why a SocketCAN interface cannot be opened, and what to do, before python-can tries.

python-can on a kernel without SocketCAN ends in "OSError: [Errno 97] Address family not
supported by protocol"; on a missing or down interface in an error that names neither.
:func:`socketcan_problem` tells the cause and the way in one line (or None when the
interface looks usable); the bus opening code (:func:`fftune.host.drive._open_bus`) and
the demo call it.
"""
import errno
import os
import socket

ARPHRD_CAN = 280          # /sys/class/net/IF/type of a CAN interface (linux/if_arp.h)
IFF_UP = 0x1              # /sys/class/net/IF/flags (linux/if.h)
SETUP_VCAN = "modprobe vcan; ip link add dev {ch} type vcan; ip link set up {ch}"


def socketcan_problem(channel, sys_net="/sys/class/net", af_can_probe=None):
    """The reason SocketCAN interface ``channel`` cannot be used and the way out (one line),
    or None.

    Checks, in order: the kernel supports AF_CAN (a raw CAN socket can be made; errno
    EAFNOSUPPORT: no SocketCAN in this kernel, see docs/vm-testing.md), the interface exists
    (``sys_net``/CHANNEL), it is a CAN interface (type 280) and it is up (IFF_UP).
    ``af_can_probe``: a callable raising OSError like ``socket.socket(AF_CAN, ...)`` would
    (tests)."""
    if not channel:
        return "no interface named (-c vcan0 or can0)"
    try:
        if af_can_probe is not None:
            af_can_probe()
        else:
            family = getattr(socket, "AF_CAN", None)
            if family is None:
                return ("this Python has no SocketCAN (socket.AF_CAN missing: not Linux?): use "
                        "-i socketcand, or a Linux kernel with SocketCAN (docs/vm-testing.md)")
            socket.socket(family, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        if exc.errno in (errno.EAFNOSUPPORT, errno.EPROTONOSUPPORT):
            return ("no SocketCAN in this kernel (address family AF_CAN not supported; `ip link add "
                    "... type vcan` answers 'Unknown device type' here): run it in the qemu guest "
                    "with a SocketCAN kernel (docs/vm-testing.md: tests/vm/guest.py run), or use "
                    "-i socketcand")
        if exc.errno in (errno.EPERM, errno.EACCES):
            return f"not allowed to open a raw CAN socket ({exc.strerror})"
        return f"cannot make a raw CAN socket ({exc.strerror or exc})"
    path = os.path.join(sys_net, channel)
    if os.sep in channel or not os.path.isdir(path):
        return (f"no such network interface {channel!r} (ip -details link show); a virtual bus: "
                + SETUP_VCAN.format(ch=channel if os.sep not in channel else "vcan0")
                + " (as root; 'Unknown device type': no vcan module, docs/vm-testing.md)")
    try:
        with open(os.path.join(path, "type"), encoding="ascii") as fh:
            kind = int(fh.read().strip())
        with open(os.path.join(path, "flags"), encoding="ascii") as fh:
            flags = int(fh.read().strip(), 0)
    except (OSError, ValueError):
        return None            # cannot tell: let python-can try
    if kind != ARPHRD_CAN:
        return f"{channel} is not a CAN interface (link type {kind}, CAN is {ARPHRD_CAN})"
    if not flags & IFF_UP:
        return f"interface {channel} is down: ip link set up {channel} (as root)"
    return None
