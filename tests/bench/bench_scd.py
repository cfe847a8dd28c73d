"""Benchmark of drive_sim's socketcand server under hostile clients (`make bench`).

1. CPU of an idle drive_sim (free-run) with 7 silent clients that finish the handshake,
   then never speak, while the drive sends heartbeats every 10 ms (output queued for them
   during the 200 ms handshake grace): new silent clients connect every 150 ms so that
   some are always in their grace. CPU = (utime + stime) of drive_sim / wall time.
2. drive_sim --realtime (2560 Hz) with 4 clients flooding the bus with frames for
   FFTUNE_BENCH_FLOOD_S seconds (default 10): steps, missed steps (a step that starts
   more than one controller period late, drive_sim's "overruns") and frames it received;
   once at normal priority (on a loaded machine the scheduler, not the bus, then causes
   most misses) and once with drive_sim at SCHED_FIFO priority 10 (`chrt -f 10`, as a
   real-time port would run its control task; skipped when not permitted), where what is
   left is what the bus work does to the deadline.

FFTUNE_DRIVE_SIM selects the binary (to compare builds). Figures depend on the machine's
load: on a shared 2-core machine they are pessimistic.
"""
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), os.pardir, os.pardir))
sys.path.insert(0, os.path.join(REPO, "tests"))
DRIVE_SIM = os.environ.get("FFTUNE_DRIVE_SIM") or os.path.join(REPO, "firmware_sim", "build", "drive_sim")
PLANT = os.path.join(REPO, "configs", "plant_twomass.yaml")
CLK_TCK = os.sysconf("SC_CLK_TCK")


def start(*extra, prefix=()):
    proc = subprocess.Popen([*prefix, DRIVE_SIM, "--can", "socketcand:127.0.0.1:0", "--config", PLANT, *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    port = int(re.search(r":(\d+), node", line).group(1))
    return proc, port


def stop(proc):
    proc.terminate()
    _, err = proc.communicate(timeout=10)
    return err


def cpu_s(pid):
    with open(f"/proc/{pid}/stat") as fh:
        f = fh.read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / CLK_TCK


def handshake(port):
    s = socket.create_connection(("127.0.0.1", port), timeout=3)
    s.recv(100)
    s.sendall(b"< open can0 >")
    s.recv(100)
    s.sendall(b"< rawmode >")
    s.recv(100)
    return s


def silent_clients_cpu(duration_s=3.0):
    from test_reliability_support import RawClient
    proc, port = start()
    try:
        cfg = RawClient(port)
        cfg.send_frame(0x601, [0x2B, 0x17, 0x10, 0x00, 10, 0, 0, 0])  # heartbeat every 10 ms
        time.sleep(0.1)
        cfg.close()
        socks = []
        t0, c0 = time.monotonic(), cpu_s(proc.pid)
        while time.monotonic() - t0 < duration_s:
            if len(socks) >= 7:  # (a closed slot frees when the server sees the EOF)
                socks.pop(0).close()
            socks.append(handshake(port))
            time.sleep(0.15)
        wall, cpu = time.monotonic() - t0, cpu_s(proc.pid) - c0
        for s in socks:
            s.close()
    finally:
        stop(proc)
    return cpu / wall


def flood(duration_s, n_clients=4, prefix=()):
    proc, port = start("--realtime", prefix=prefix)
    stop_flag = threading.Event()

    def talker():
        s = handshake(port)
        s.setblocking(False)
        burst = b"< send 77f 8 01 02 03 04 05 06 07 08 >" * 200
        pending = b""
        while not stop_flag.is_set():
            try:
                pending = pending[s.send(pending or burst):] if pending else burst[s.send(burst):]
            except BlockingIOError:
                time.sleep(0.0005)
            except OSError:
                break
            try:
                while s.recv(65536):
                    pass
            except (BlockingIOError, OSError):
                pass
        s.close()

    threads = [threading.Thread(target=talker, daemon=True) for _ in range(n_clients)]
    for t in threads:
        t.start()
    c0 = cpu_s(proc.pid)
    time.sleep(duration_s)
    print(f"  drive_sim CPU during the flood: {(cpu_s(proc.pid) - c0) / duration_s * 100:.0f} %")
    stop_flag.set()
    for t in threads:
        t.join(5)
    err = stop(proc)
    m = re.search(r"(\d+) steps, (\d+) overruns, (\d+) frames received", err)
    late = re.search(r"(\d+) periods with bus work past", err)
    return tuple(int(x) for x in m.groups()) if m else (None, None, None), late and int(late.group(1))


def main():
    print(f"drive_sim: {DRIVE_SIM}")
    load = os.getloadavg()[0]
    print(f"load average {load:.1f} on {os.cpu_count()} cores (figures are pessimistic under load)")
    share = silent_clients_cpu()
    print(f"idle drive_sim with silent socketcand clients in their handshake grace: {share * 100:.1f} % CPU")
    seconds = float(os.environ.get("FFTUNE_BENCH_FLOOD_S", "10"))
    fifo = subprocess.run(["chrt", "-f", "10", "true"], capture_output=True).returncode == 0 \
        if shutil.which("chrt") else False
    for label, prefix in (("normal priority", ()), ("SCHED_FIFO 10", ("chrt", "-f", "10"))):
        if prefix and not fifo:
            print(f"--realtime under SCHED_FIFO: skipped (chrt -f not permitted here)")
            continue
        (steps, overruns, frames), late = flood(seconds, prefix=prefix)
        if steps is None:
            print("flood: drive_sim printed no statistics")
            return 1
        print(f"--realtime ({label}), 4 flooding clients, {seconds:g} s: {steps} steps "
              f"({steps / seconds / 2560:.0%} of 2560 Hz), {overruns} missed steps (started > 1 period "
              f"late), {frames} frames received"
              + (f", {late} periods whose bus work reached the next deadline" if late is not None else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
