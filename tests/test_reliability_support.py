"""Helpers of the reliability tests (tests/test_reliability_*.py), and tests of the helpers.

- :func:`start_drive` starts ``drive_sim`` (the ASan + UBSan build ``build/asan/drive_sim``
  from ``make test`` when it exists, else ``build/drive_sim``) on a free loopback port and
  :meth:`Drive.stop` checks that it ended without a sanitizer report.
- :class:`SocketcandProxy` sits on the socketcand TCP link between python-can and the
  drive, parses the ``< ... >`` messages and drops or delays CAN frames at random (seeded),
  in both directions; the handshake passes untouched.
- :class:`RawClient` speaks the socketcand protocol directly (handshake, ``send``, frames).
"""
import os
import random
import re
import select
import signal
import socket
import subprocess
import threading
import time

import pytest

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir))
BUILD = os.path.join(REPO, "firmware_sim", "build")
EDS = os.path.join(BUILD, "gen", "fftune_drive.eds")
PLANT = os.path.join(REPO, "configs", "plant_twomass.yaml")
SANITIZER_MARKS = ("ERROR: AddressSanitizer", "ERROR: LeakSanitizer", "runtime error:")


def drive_sim_binary():
    """The sanitizer build when `make test` made it, else the normal one (or None)."""
    for path in (os.path.join(BUILD, "asan", "drive_sim"), os.path.join(BUILD, "drive_sim")):
        if os.path.exists(path) and os.access(path, os.X_OK):
            return path
    return None


def missing_reason():
    if drive_sim_binary() is None:
        return "firmware_sim/build/drive_sim not built (run `make setup` or `make -C firmware_sim all`)"
    if not os.path.exists(EDS):
        return "firmware_sim/build/gen/fftune_drive.eds not generated (run `make -C firmware_sim all`)"
    return None


needs_drive = pytest.mark.skipif(missing_reason() is not None, reason=missing_reason() or "")


class Drive:
    """A running drive_sim; stderr goes to ``log_path``."""

    def __init__(self, proc, port, log_path, binary):
        self.proc, self.port, self.log_path, self.binary = proc, port, log_path, binary

    def alive(self):
        return self.proc.poll() is None

    def kill(self):
        """SIGKILL (a crash or a power cut of the drive)."""
        if self.alive():
            self.proc.kill()
        self.proc.wait(5)

    def stop(self, check=True):
        """SIGTERM; with ``check``, fail on a sanitizer report or an abnormal exit."""
        if self.alive():
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
                raise AssertionError("drive_sim did not stop on SIGTERM within 10 s")
        if self.proc.stdout:
            self.proc.stdout.close()
        if check:
            log = self.log()
            for mark in SANITIZER_MARKS:
                assert mark not in log, f"drive_sim ({self.binary}) reported: {log[-3000:]}"
            assert self.proc.returncode == 0, f"drive_sim exit code {self.proc.returncode}: {log[-2000:]}"

    def log(self):
        try:
            with open(self.log_path, errors="replace") as fh:
                return fh.read()
        except OSError:
            return ""


_LISTEN = re.compile(r"listening on socketcand ([\d.]+):(\d+)")


def start_drive(tmp_path, *extra, port=0, binary=None, name="drive_sim"):
    """Start drive_sim on 127.0.0.1:port (0: a free port) and wait for its listening line."""
    binary = binary or drive_sim_binary()
    log_path = os.path.join(str(tmp_path), f"{name}.{time.monotonic_ns()}.log")
    env = dict(os.environ, ASAN_OPTIONS="detect_leaks=1:halt_on_error=1",
               UBSAN_OPTIONS="print_stacktrace=1:halt_on_error=1")
    args = [binary, "--config", PLANT]
    if not any(a.startswith("socketcand:") for a in extra):
        args += ["--port", str(port)]
    with open(log_path, "w") as log:
        proc = subprocess.Popen(args + list(extra), stdout=subprocess.PIPE, stderr=log, text=True,
                                env=env)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stdout], [], [], 0.1)
        if ready:
            line = proc.stdout.readline()
            m = _LISTEN.search(line)
            if m:
                drive = Drive(proc, int(m.group(2)), log_path, binary)
                drive.bound_host = m.group(1)
                threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()
                return drive
        if proc.poll() is not None:
            break
    proc.kill()
    proc.wait()
    raise AssertionError(f"drive_sim did not start: {open(log_path).read()[-2000:]}")


# ---- raw socketcand client -------------------------------------------------------------

class RawClient:
    """A socketcand rawmode client on a plain socket."""

    def __init__(self, port, host="127.0.0.1", handshake=True, timeout=5.0):
        self.sock = socket.create_connection((host, port), timeout=timeout)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buf = b""
        if handshake:
            assert self.expect_message(timeout) == b"< hi >"
            self.sock.sendall(b"< open can0 >")
            assert self.expect_message(timeout) == b"< ok >"
            self.sock.sendall(b"< rawmode >")
            assert self.expect_message(timeout) == b"< ok >"

    def close(self):
        self.sock.close()

    def expect_message(self, timeout=5.0):
        """The next ``< ... >`` message (bytes), or None at EOF / timeout."""
        deadline = time.monotonic() + timeout
        while True:
            start = self.buf.find(b"<")
            end = self.buf.find(b">", start + 1) if start >= 0 else -1
            if start >= 0 and end >= 0:
                msg, self.buf = self.buf[start:end + 1], self.buf[end + 1:]
                return msg
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self.sock.settimeout(left)
            try:
                chunk = self.sock.recv(65536)
            except socket.timeout:
                return None
            except ConnectionError:
                return None
            if not chunk:
                return None
            self.buf += chunk

    def send_frame(self, can_id, data):
        body = " ".join(f"{b:x}" for b in data)
        self.sock.sendall(f"< send {can_id:x} {len(data)} {body} >".encode())

    def frames(self, timeout=2.0):
        """Yield (id, data) of received frames until nothing arrives for ``timeout`` s."""
        while True:
            msg = self.expect_message(timeout)
            if msg is None:
                return
            parts = msg[1:-1].split()
            if len(parts) >= 3 and parts[0] == b"frame":
                data = bytes.fromhex(parts[3].decode()) if len(parts) >= 4 else b""
                yield int(parts[1], 16), data

    def sdo_upload_expedited(self, index, sub, node=1, timeout=2.0):
        """Expedited SDO upload; returns the 8 response bytes (or None on timeout)."""
        req = [0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0]
        self.send_frame(0x600 + node, req)
        deadline = time.monotonic() + timeout
        for cid, data in self.frames(timeout):
            if cid == 0x580 + node and len(data) == 8 and data[1] == req[1] and data[2] == req[2] \
                    and data[3] == sub:
                return data
            if time.monotonic() > deadline:
                break
        return None


# ---- fault-injecting proxy -------------------------------------------------------------

class SocketcandProxy:
    """TCP proxy for the socketcand protocol that drops / delays CAN frames.

    Parameters
    ----------
    upstream_port : int
        The drive's socketcand port on 127.0.0.1.
    drop : float
        Probability that a frame (``< frame ... >`` to the host, ``< send ... >`` to the
        drive) is dropped, each direction independently.
    delay : float
        Probability that the link stalls before a frame for a random 2-30 ms (frames keep
        their order, as on a CAN bus).
    seed : int
        Seed of the random decisions (one generator per direction and connection).
    """

    def __init__(self, upstream_port, drop=0.0, delay=0.0, seed=0):
        self.upstream_port = upstream_port
        self.drop, self.delay, self.seed = drop, delay, seed
        self.lsock = socket.socket()
        self.lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.lsock.bind(("127.0.0.1", 0))
        self.lsock.listen(4)
        self.port = self.lsock.getsockname()[1]
        self.stats = {"frames": 0, "dropped": 0, "delayed": 0}
        self._lock = threading.Lock()
        self._closing = False
        self._socks = []
        self._nconn = 0
        threading.Thread(target=self._accept, daemon=True, name="proxy-accept").start()

    def _accept(self):
        while not self._closing:
            try:
                down, _ = self.lsock.accept()
            except OSError:
                return
            try:
                up = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=5)
            except OSError:
                down.close()
                continue
            for s in (down, up):
                s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                s.settimeout(None)
            self._socks += [down, up]
            self._nconn += 1
            base = self.seed * 1000 + self._nconn * 2
            threading.Thread(target=self._pump, args=(up, down, random.Random(base)), daemon=True).start()
            threading.Thread(target=self._pump, args=(down, up, random.Random(base + 1)), daemon=True).start()

    def _pump(self, src, dst, rng):
        buf = b""
        try:
            while True:
                chunk = src.recv(65536)
                if not chunk:
                    break
                buf += chunk
                out = []
                while True:
                    start = buf.find(b"<")
                    end = buf.find(b">", start + 1) if start >= 0 else -1
                    if start < 0 or end < 0:
                        break
                    msg, buf = buf[start:end + 1], buf[end + 1:]
                    if msg.startswith((b"< frame ", b"< send ")):
                        with self._lock:
                            self.stats["frames"] += 1
                        if rng.random() < self.drop:
                            with self._lock:
                                self.stats["dropped"] += 1
                            continue
                        if rng.random() < self.delay:
                            with self._lock:
                                self.stats["delayed"] += 1
                            if out:
                                dst.sendall(b"".join(out))
                                out = []
                            time.sleep(rng.uniform(0.002, 0.030))
                        out.append(msg)
                    else:
                        # handshake: alone in its write, as python-can reads it
                        if out:
                            dst.sendall(b"".join(out))
                            out = []
                        dst.sendall(msg)
                if out:
                    dst.sendall(b"".join(out))
        except OSError:
            pass
        for s in (src, dst):
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def close(self):
        self._closing = True
        try:
            self.lsock.close()
        except OSError:
            pass
        for s in self._socks:
            try:
                s.close()
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ---- tests of the helpers ---------------------------------------------------------------

@needs_drive
def test_proxy_without_faults_is_transparent(tmp_path):
    drive = start_drive(tmp_path)
    try:
        with SocketcandProxy(drive.port) as proxy:
            cli = RawClient(proxy.port)
            resp = cli.sdo_upload_expedited(0x1000, 0)
            cli.close()
            assert resp is not None and resp[0] == 0x43
            assert int.from_bytes(resp[4:8], "little") == 0x00020192
            assert proxy.stats["dropped"] == 0 and proxy.stats["frames"] >= 2
    finally:
        drive.stop()


@needs_drive
def test_proxy_drops_about_the_requested_share(tmp_path):
    drive = start_drive(tmp_path)
    try:
        with SocketcandProxy(drive.port, drop=0.05, seed=3) as proxy:
            cli = RawClient(proxy.port)
            answered = sum(cli.sdo_upload_expedited(0x1000, 0, timeout=0.3) is not None for _ in range(200))
            cli.close()
            # request and answer each pass with p = 0.95: about 90 % of 200 round trips
            assert 160 <= answered <= 199, answered
            assert 0.02 < proxy.stats["dropped"] / proxy.stats["frames"] < 0.09, proxy.stats
    finally:
        drive.stop()
