#!/usr/bin/env python3
"""Run pytest for each mutant without paying Python's start-up and numpy/scipy imports.

    forkserver.py serve SOCKET          # imports numpy, scipy, pytest once, then waits
    forkserver.py run SOCKET ARGS...    # cosmic-ray's test command: pytest ARGS in a fork
    forkserver.py run SOCKET --map MAP --module FILE ARGS...
                                        # only the tests that execute the mutated statements
                                        # (tools/mutation/testmap.py); ARGS' test paths are
                                        # replaced by their node ids under --rootdir

Each `run` connects to the server, which forks; the child runs ``pytest.main(ARGS)`` (it
imports the package under test itself, fresh, so it sees the mutant just written) and
its exit status is sent back and becomes the client's. The server never imports the
package under test. If the client goes away (cosmic-ray's timeout kills it), the child
is killed. Writing .pyc files is off: a mutant written within the same second as the
previous one must not be taken from a stale cache.
"""
import json
import os
import select
import signal
import socket
import sys


def serve(path):
    sys.dont_write_bytecode = True
    import numpy  # noqa: F401  (the point: imported once)
    import pytest  # noqa: F401
    import scipy.fft  # noqa: F401
    import scipy.signal  # noqa: F401
    import scipy.optimize  # noqa: F401
    import scipy.special  # noqa: F401
    import scipy.stats  # noqa: F401  (binom, t: 1.5 s to import)

    if os.path.exists(path):
        os.unlink(path)
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(4)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    print("forkserver: ready", flush=True)
    while True:
        conn, _ = srv.accept()
        with conn:
            data = b""
            while not data.endswith(b"\n"):
                chunk = conn.recv(65536)
                if not chunk:
                    break
                data += chunk
            if not data.endswith(b"\n"):
                continue
            req = json.loads(data)
            pid = os.fork()
            if pid == 0:                                   # child: one pytest run
                srv.close()
                conn.close()
                os.setsid()
                os.chdir(req["cwd"])
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, 1)
                os.dup2(devnull, 2)
                code = 3
                try:
                    import pytest as pt
                    code = int(pt.main(req["args"]))
                finally:
                    os._exit(code)
            status = None
            while status is None:
                ready, _, _ = select.select([conn], [], [], 0.05)
                done, st = os.waitpid(pid, os.WNOHANG)
                if done:
                    status = os.waitstatus_to_exitcode(st)
                    break
                if ready and not conn.recv(1):             # client gone: stop the child
                    try:
                        os.killpg(pid, signal.SIGKILL)
                    except OSError:
                        pass
                    os.waitpid(pid, 0)
                    break
            if status is not None:
                try:
                    conn.sendall(f"{status}\n".encode())
                except OSError:
                    pass


def _narrow(args):
    """ARGS with --map/--module taken out; the test paths replaced by the node ids the map
    selects for the mutant in FILE (unchanged where the map selects the whole selection)."""
    if len(args) < 4 or args[0] != "--map" or args[2] != "--module":
        return args
    map_path, module, args = args[1], args[3], args[4:]
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import testmap
    nodes = testmap.select(map_path, module)
    if nodes is None:
        return args
    root = next(a.split("=", 1)[1] for a in args if a.startswith("--rootdir="))
    return [a for a in args if a.startswith("-")] + [os.path.join(root, n) for n in nodes]


def run(path, args):
    args = _narrow(args)
    cli = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    cli.connect(path)
    cli.sendall((json.dumps({"cwd": os.getcwd(), "args": args}) + "\n").encode())
    reply = b""
    while not reply.endswith(b"\n"):
        chunk = cli.recv(64)
        if not chunk:
            print("forkserver: no answer (server stopped?)", file=sys.stderr)
            return 3
        reply += chunk
    code = int(reply)
    return code if code >= 0 else 128 - code       # killed by a signal: non-zero


if __name__ == "__main__":
    if len(sys.argv) >= 3 and sys.argv[1] == "serve":
        serve(sys.argv[2])
    elif len(sys.argv) >= 3 and sys.argv[1] == "run":
        sys.exit(run(sys.argv[2], sys.argv[3:]))
    else:
        print(__doc__, file=sys.stderr)
        sys.exit(2)
