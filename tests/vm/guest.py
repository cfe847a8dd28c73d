#!/usr/bin/env python3
"""Run a command inside a throw-away qemu guest that has SocketCAN (vcan0).

This machine's kernel may have no CAN support; Debian's packaged kernel has ``can``,
``can-raw`` and ``vcan`` as modules. This module boots that kernel under
``qemu-system-x86_64 -accel tcg`` with a small initramfs (busybox-static + the modules,
resolved through ``modules.dep``), shares the host's ``/`` read-only over virtio-9p, makes it
writable in the guest through an overlay on a tmpfs, creates ``vcan0``, chroots into the host
tree, runs one command with a given environment and working directory, hands back its
output and exit status, and powers off. See docs/vm-testing.md.

Library use (tests go through tests/vmguest.py)::

    available, reason = guest_available()
    result = run_in_guest("candump -n 1 vcan0", timeout_s=60)

Command line::

    python tests/vm/guest.py check
    python tests/vm/guest.py build
    python tests/vm/guest.py run [--cwd DIR] [--env K=V ...] [--timeout S] [--out DIR] -- COMMAND [ARG ...]

``--out DIR``: what the command writes under $FFTUNE_VM_OUT (/run/vmjob/out) comes back into
DIR on the host, byte for byte (the host tree is read-only in the guest: its writes elsewhere
vanish at power-off); the text ``{out}`` in the command's arguments stands for that path,
e.g. ``-- .venv/bin/fftune demo -i socketcan -c vcan0 --config configs/demo_vm.yaml --out {out}/demo``.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import lzma
import gzip
import os
import shlex
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

VM_DIR = Path(__file__).resolve().parent
REPO_ROOT = VM_DIR.parent.parent
CACHE_DIR = REPO_ROOT / "build" / "vm"
GUEST_INIT = VM_DIR / "guest_init.sh"

# Bump when the initramfs layout produced below changes (part of the cache key).
INITRAMFS_FORMAT = 1

# What the guest loads. Order does not matter: dependencies come from modules.dep.
GUEST_MODULES = (
    "virtio_pci", "virtio_mmio", "9pnet_virtio", "9p", "overlay",
    "can", "can_raw", "can_bcm", "vcan",  # can_bcm: python-can send_periodic on socketcan
)

DEFAULT_GUEST_ENV = {
    "PATH": "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
    "HOME": "/root",
    "TMPDIR": "/tmp",
    "LANG": "C.UTF-8",
    "TERM": "dumb",
    "PYTHONDONTWRITEBYTECODE": "1",
    "MPLBACKEND": "Agg",
    # Lets code (and guest_available) know it already runs inside the guest.
    "FFTUNE_IN_VM_GUEST": "1",
    # The job directory (read-write, shared with the host) and its "out" subdirectory: files
    # written to FFTUNE_VM_OUT come back in GuestResult.outputs.
    "FFTUNE_VM_JOB": "/run/vmjob",
    "FFTUNE_VM_OUT": "/run/vmjob/out",
}

# Seconds the host waits beyond the command's own timeout for boot, setup and power-off
# before it kills qemu. Boot-run-poweroff of `true` takes 7-25 s under TCG on a shared
# 2-core machine.
BOOT_ALLOWANCE_S = 120.0


class GuestUnavailable(RuntimeError):
    """Something the guest needs (qemu, kernel, modules, busybox-static, cpio) is missing."""


@dataclasses.dataclass(frozen=True)
class GuestKernel:
    version: str
    vmlinuz: Path
    modules_dir: Path


@dataclasses.dataclass
class GuestResult:
    """Outcome of one guest run, shaped like subprocess.CompletedProcess.

    Attributes
    ----------
    args : command as given.
    returncode : exit status of the command in the guest; 125 when the guest setup
        failed (see ``init_log``), -9 when it was killed by the timeout, None when the guest
        never reported (qemu died or the host hard limit hit).
    stdout, stderr : the command's output (str).
    timed_out : True when the in-guest watchdog or the host hard limit ended the run.
    init_log : the guest init's log (module loading, mounts, setup timing).
    console : the guest's serial console (kernel messages).
    duration_s : host wall-clock time from qemu start to its exit, seconds.
    outputs : {name: text} of the files the command wrote under $FFTUNE_VM_OUT
        (names relative to it, subdirectories with '/').
    """

    args: object
    returncode: int | None
    stdout: str
    stderr: str
    timed_out: bool = False
    init_log: str = ""
    console: str = ""
    duration_s: float = 0.0
    outputs: dict = dataclasses.field(default_factory=dict)

    def check_returncode(self):
        if self.returncode != 0:
            raise subprocess.CalledProcessError(self.returncode if self.returncode is not None
                                                else -1, self.args, self.stdout, self.stderr)

    def describe(self) -> str:
        """All diagnostics in one text, for assertion messages."""
        return (f"command {self.args!r}: returncode {self.returncode}, timed_out {self.timed_out}, "
                f"{self.duration_s:.1f} s\n--- stdout\n{self.stdout}\n--- stderr\n{self.stderr}"
                f"\n--- init.log\n{self.init_log}\n--- console (last 3000 chars)\n"
                f"{self.console[-3000:]}")


def _is_static_elf(path: Path) -> bool:
    """True when ``path`` is an ELF executable without a program interpreter (PT_INTERP)."""
    with open(path, "rb") as f:
        head = f.read(64)
        if head[:4] != b"\x7fELF" or head[4] != 2:  # 64-bit only (x86-64 guest)
            return False
        endian = "<" if head[5] == 1 else ">"
        phoff, = struct.unpack_from(endian + "Q", head, 32)
        phentsize, phnum = struct.unpack_from(endian + "HH", head, 54)
        f.seek(phoff)
        table = f.read(phentsize * phnum)
    return all(struct.unpack_from(endian + "I", table, i * phentsize)[0] != 3
               for i in range(phnum))


def find_qemu() -> str:
    wanted = os.environ.get("FFTUNE_VM_QEMU")
    if wanted:
        if not (os.path.isfile(wanted) and os.access(wanted, os.X_OK)):
            raise GuestUnavailable(f"FFTUNE_VM_QEMU={wanted} is not an executable file")
        return wanted
    qemu = shutil.which("qemu-system-x86_64")
    if not qemu:
        raise GuestUnavailable("qemu-system-x86_64 not found (Debian package qemu-system-x86)")
    return qemu


def find_kernel() -> GuestKernel:
    """The newest kernel in /boot that has vcan and 9p as modules (or FFTUNE_VM_KERNEL=version)."""
    wanted = os.environ.get("FFTUNE_VM_KERNEL")
    modules_root = Path("/lib/modules")
    versions = ([wanted] if wanted else
                sorted((p.name for p in modules_root.iterdir()), reverse=True)
                if modules_root.is_dir() else [])
    problems = []
    for version in versions:
        vmlinuz = Path("/boot") / f"vmlinuz-{version}"
        mdir = modules_root / version
        if not vmlinuz.is_file():
            problems.append(f"{version}: no {vmlinuz}")
            continue
        if not os.access(vmlinuz, os.R_OK):
            problems.append(f"{version}: {vmlinuz} not readable by this user")
            continue
        if not (mdir / "modules.dep").is_file():
            problems.append(f"{version}: no {mdir}/modules.dep")
            continue
        try:
            _resolve_modules(mdir, GUEST_MODULES)
        except GuestUnavailable as exc:
            problems.append(f"{version}: {exc}")
            continue
        return GuestKernel(version, vmlinuz, mdir)
    detail = "; ".join(problems) if problems else "no kernel under /lib/modules"
    raise GuestUnavailable("no bootable kernel with vcan modules (Debian package "
                           f"linux-image-amd64): {detail}")


def find_busybox() -> Path:
    for candidate in (os.environ.get("FFTUNE_VM_BUSYBOX"), "/bin/busybox", "/usr/bin/busybox"):
        if candidate and Path(candidate).is_file() and _is_static_elf(Path(candidate)):
            return Path(candidate)
    raise GuestUnavailable("no statically linked busybox (Debian package busybox-static)")


def find_cpio() -> str:
    cpio = shutil.which("cpio")
    if not cpio:
        raise GuestUnavailable("cpio not found (Debian package cpio)")
    return cpio


def _module_key(name: str) -> str:
    """Kernel module names treat '-' and '_' alike; strip the directory and .ko[.xz|.gz|.zst]."""
    base = name.rsplit("/", 1)[-1]
    base = base.split(".ko", 1)[0]
    return base.replace("-", "_")


def _resolve_modules(modules_dir: Path, names) -> list[str]:
    """Paths (relative to ``modules_dir``) of ``names`` and their dependencies, dependencies first.

    Modules built into the kernel (modules.builtin) need no file and are left out.
    """
    deps = {}
    paths = {}
    for line in (modules_dir / "modules.dep").read_text().splitlines():
        if ":" not in line:
            continue
        path, rest = line.split(":", 1)
        key = _module_key(path)
        paths[key] = path
        deps[key] = [_module_key(d) for d in rest.split()]
    builtin_file = modules_dir / "modules.builtin"
    builtin = ({_module_key(p) for p in builtin_file.read_text().split()}
               if builtin_file.is_file() else set())
    order: list[str] = []
    visiting = set()

    def visit(key):
        if key in builtin or paths.get(key) in order:
            return
        if key not in paths:
            raise GuestUnavailable(f"kernel module {key} neither in modules.dep nor built in")
        if key in visiting:
            raise GuestUnavailable(f"dependency loop at kernel module {key}")
        visiting.add(key)
        for dep in deps[key]:
            visit(dep)
        visiting.discard(key)
        order.append(paths[key])

    for name in names:
        visit(_module_key(name))
    return order


def _read_module(path: Path) -> bytes:
    """Module bytes, decompressed (busybox insmod may not read compressed modules)."""
    data = path.read_bytes()
    if path.name.endswith(".ko.xz"):
        return lzma.decompress(data)
    if path.name.endswith(".ko.gz"):
        return gzip.decompress(data)
    if path.name.endswith(".ko.zst"):
        zstd = shutil.which("zstd")
        if not zstd:
            raise GuestUnavailable(f"{path} is zstd-compressed and zstd is not installed")
        return subprocess.run([zstd, "-dc", str(path)], capture_output=True, check=True).stdout
    return data


def _has_pvh_entry(elf: bytes) -> bool:
    """True when a 64-bit ELF kernel has the Xen PVH entry note qemu needs to boot it directly."""
    if elf[:4] != b"\x7fELF" or elf[4] != 2 or elf[5] != 1:
        return False
    phoff, = struct.unpack_from("<Q", elf, 32)
    phentsize, phnum = struct.unpack_from("<HH", elf, 54)
    for i in range(phnum):
        p_type, _flags, p_offset, _vaddr, _paddr, p_filesz = struct.unpack_from(
            "<IIQQQQ", elf, phoff + i * phentsize)
        if p_type != 4:  # PT_NOTE
            continue
        pos, end = p_offset, p_offset + p_filesz
        while pos + 12 <= end:
            namesz, descsz, n_type = struct.unpack_from("<III", elf, pos)
            name = elf[pos + 12:pos + 12 + namesz].rstrip(b"\0")
            if name == b"Xen" and n_type == 18:  # XEN_ELFNOTE_PHYS32_ENTRY
                return True
            pos += 12 + (namesz + 3) // 4 * 4 + (descsz + 3) // 4 * 4
    return False


def _decompress_bzimage(data: bytes) -> bytes | None:
    """The vmlinux ELF inside a bzImage, or None when no known compressed payload is found."""
    for magic, kind in ((b"\xfd7zXZ\x00", "xz"), (b"\x28\xb5\x2f\xfd", "zstd"),
                        (b"\x1f\x8b\x08", "gzip")):
        start = data.find(magic)
        while start >= 0:
            try:
                if kind == "xz":
                    out = lzma.LZMADecompressor().decompress(data[start:])
                elif kind == "gzip":
                    out = zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(data[start:])
                else:
                    zstd = shutil.which("zstd")
                    if not zstd:
                        break
                    out = subprocess.run([zstd, "-dc"], input=data[start:],
                                         capture_output=True).stdout
            except (lzma.LZMAError, zlib.error):
                out = b""
            if out[:4] == b"\x7fELF":
                return out
            start = data.find(magic, start + 1)
    return None


def boot_image(kernel: GuestKernel, cache_dir: Path = CACHE_DIR) -> Path:
    """What to pass to qemu -kernel: the decompressed vmlinux when it has a PVH entry, else vmlinuz.

    Why: under TCG the bzImage decompressing itself (xz) takes 10-20 s of emulated CPU; qemu
    boots an uncompressed vmlinux with a PVH note directly. Cached in ``cache_dir`` and keyed
    by the vmlinuz's size and mtime; falls back to the vmlinuz when extraction fails.
    """
    stat = kernel.vmlinuz.stat()
    key = f"{kernel.vmlinuz} {stat.st_size} {stat.st_mtime_ns}"
    vmlinux = cache_dir / f"vmlinux-{kernel.version}"
    key_file = cache_dir / f"vmlinux-{kernel.version}.key"
    if vmlinux.is_file() and key_file.is_file() and key_file.read_text().strip() == key:
        return vmlinux
    if key_file.is_file() and key_file.read_text().strip() == "none " + key:
        return kernel.vmlinuz
    cache_dir.mkdir(parents=True, exist_ok=True)
    elf = _decompress_bzimage(kernel.vmlinuz.read_bytes())
    tmp_key = key_file.with_suffix(f".key.{os.getpid()}")
    if elf is None or not _has_pvh_entry(elf):
        tmp_key.write_text("none " + key + "\n")
        os.replace(tmp_key, key_file)
        return kernel.vmlinuz
    tmp = vmlinux.with_name(vmlinux.name + f".{os.getpid()}")
    tmp.write_bytes(elf)
    os.replace(tmp, vmlinux)
    tmp_key.write_text(key + "\n")
    os.replace(tmp_key, key_file)
    return vmlinux


def build_initramfs(kernel: GuestKernel | None = None, cache_dir: Path = CACHE_DIR,
                    force: bool = False) -> Path:
    """The initramfs for ``kernel``, built into ``cache_dir`` unless its inputs are unchanged.

    The cache key hashes the init script, busybox, every module file and the format
    version; the archive is written to a temp file and renamed, so concurrent builders never
    see half an archive.
    """
    kernel = kernel or find_kernel()
    busybox = find_busybox()
    cpio = find_cpio()
    modules = _resolve_modules(kernel.modules_dir, GUEST_MODULES)

    digest = hashlib.sha256()
    digest.update(f"format {INITRAMFS_FORMAT} kernel {kernel.version}\n".encode())
    for part in [GUEST_INIT, busybox] + [kernel.modules_dir / m for m in modules]:
        digest.update(str(part).encode() + b"\0" + part.read_bytes())
    key = digest.hexdigest()

    cache_dir.mkdir(parents=True, exist_ok=True)
    archive = cache_dir / f"initramfs-{kernel.version}.cpio"
    key_file = cache_dir / f"initramfs-{kernel.version}.key"
    if not force and archive.is_file() and key_file.is_file() \
            and key_file.read_text().strip() == key:
        return archive

    with tempfile.TemporaryDirectory(dir=cache_dir, prefix="staging-") as staging:
        root = Path(staging) / "root"
        (root / "bin").mkdir(parents=True)
        (root / "lib" / "modules").mkdir(parents=True)
        shutil.copy2(busybox, root / "bin" / "busybox")
        os.chmod(root / "bin" / "busybox", 0o755)
        os.symlink("busybox", root / "bin" / "sh")
        shutil.copy2(GUEST_INIT, root / "init")
        os.chmod(root / "init", 0o755)
        load_lines = []
        for rel in modules:
            target = root / "lib" / "modules" / (_module_key(rel) + ".ko")
            target.write_bytes(_read_module(kernel.modules_dir / rel))
            load_lines.append("/" + str(target.relative_to(root)))
        (root / "modules.load").write_text("\n".join(load_lines) + "\n")

        names = sorted(str(p.relative_to(root)) for p in root.rglob("*"))
        tmp_archive = Path(staging) / "initramfs.cpio"
        with open(tmp_archive, "wb") as out:
            subprocess.run([cpio, "--quiet", "-o", "-H", "newc", "-R", "0:0"],
                           input="\n".join(names).encode() + b"\n", stdout=out,
                           cwd=root, check=True)
        os.replace(tmp_archive, archive)
    tmp_key = key_file.with_suffix(f".key.{os.getpid()}")
    tmp_key.write_text(key + "\n")
    os.replace(tmp_key, key_file)
    return archive


def guest_available() -> tuple[bool, str]:
    """(True, description) when everything the guest needs is installed, else (False, reason)."""
    if os.environ.get("FFTUNE_IN_VM_GUEST") == "1":
        return False, "already inside the qemu test guest (no nested guests)"
    try:
        qemu = find_qemu()
        kernel = find_kernel()
        find_busybox()
        find_cpio()
    except GuestUnavailable as exc:
        return False, str(exc)
    return True, f"{qemu} with kernel {kernel.version}"


def _job_script(command, env: dict, cwd: str) -> str:
    """The shell script the guest runs inside the chroot (under /usr/bin/env -i)."""
    lines = ["# generated by tests/vm/guest.py"]
    for key, value in env.items():
        if not key.isidentifier():
            raise ValueError(f"environment variable name {key!r} is not a shell identifier")
        lines.append(f"export {key}={shlex.quote(str(value))}")
    lines.append(f"cd {shlex.quote(cwd)} || exit 126")
    if isinstance(command, str):
        lines.append(f"exec /bin/sh -c {shlex.quote(command)}")
    else:
        lines.append("exec " + shlex.join(str(a) for a in command))
    return "\n".join(lines) + "\n"


def _read_text(path: Path) -> str:
    try:
        return path.read_bytes().decode("utf-8", errors="replace")
    except FileNotFoundError:
        return ""


def run_in_guest(command, env: dict | None = None, cwd: str | os.PathLike | None = None,
                 timeout_s: float = 300.0, files: dict | None = None, memory_mib: int = 1536, cpus: int = 2,
                 hard_limit_s: float | None = None, out_dir: str | os.PathLike | None = None) -> GuestResult:
    """Boot the guest, run ``command`` in the host tree with vcan0 up, power off.

    Parameters
    ----------
    command : str or sequence of str
        A str runs through ``/bin/sh -c``; a sequence is executed as is.
    env : dict, optional
        Environment of the command, on top of DEFAULT_GUEST_ENV (the host's environment is
        not passed on).
    cwd : path, optional
        Working directory in the guest (the host tree is mounted at /); default the repo root.
    timeout_s : float
        Limit on the command in the guest, seconds; the guest kills its process group then.
    files : dict, optional
        {name: str or bytes} written into the job directory before boot; the command sees
        them as $FFTUNE_VM_JOB/name (/run/vmjob/name). The host's /tmp is visible in the
        guest as it was at boot (writes stay in the guest), but files written while the guest
        runs are not: pass scripts this way or inline.
    memory_mib, cpus : guest RAM (also holds everything written in the guest) and vCPUs.
    hard_limit_s : float, optional
        Host-side limit for the whole qemu run; default ``timeout_s + BOOT_ALLOWANCE_S``.
    out_dir : path, optional
        The files the command wrote under $FFTUNE_VM_OUT are copied here (binary, the tree
        kept; existing files replaced), also after a failure or a timeout.

    Returns
    -------
    GuestResult
    """
    qemu = find_qemu()
    kernel = find_kernel()
    initramfs = build_initramfs(kernel)
    image = boot_image(kernel)
    full_env = dict(DEFAULT_GUEST_ENV)
    full_env.update(env or {})
    cwd = os.fspath(cwd) if cwd is not None else str(REPO_ROOT)
    hard_limit_s = timeout_s + BOOT_ALLOWANCE_S if hard_limit_s is None else hard_limit_s

    with tempfile.TemporaryDirectory(prefix="fftune-vm-") as tmp:
        job = Path(tmp) / "job"
        job.mkdir()
        (job / "job.sh").write_text(_job_script(command, full_env, cwd))
        (job / "timeout_s").write_text(f"{max(1, int(round(timeout_s)))}\n")
        (job / "out").mkdir()
        for name, content in (files or {}).items():
            if "/" in name or name in ("job.sh", "timeout_s", "out", "stdout", "stderr", "rc",
                                       "timed_out", "init.log"):
                raise ValueError(f"files: {name!r} is not a plain file name or is reserved")
            (job / name).write_bytes(content.encode() if isinstance(content, str) else content)
        console = Path(tmp) / "console.log"
        argv = [
            qemu, "-accel", "tcg", "-M", "pc", "-cpu", os.environ.get("FFTUNE_VM_CPU", "max"), "-smp", str(cpus),
            "-m", str(memory_mib), "-nodefaults", "-no-user-config", "-display", "none",
            "-no-reboot",
            "-kernel", str(image), "-initrd", str(initramfs),
            "-append", os.environ.get("FFTUNE_VM_APPEND", "console=ttyS0 quiet panic=-1 rdinit=/init"),
            "-serial", f"file:{console}",
            "-fsdev", "local,id=hostroot,path=/,security_model=none,readonly=on,multidevs=remap",
            "-device", "virtio-9p-pci,fsdev=hostroot,mount_tag=hostroot",
            "-fsdev", f"local,id=job,path={job},security_model=none",
            "-device", "virtio-9p-pci,fsdev=job,mount_tag=job",
        ]
        start = time.monotonic()
        host_timed_out = False
        try:
            proc = subprocess.run(argv, stdin=subprocess.DEVNULL, capture_output=True,
                                  timeout=hard_limit_s)
            qemu_err = proc.stderr.decode(errors="replace")
        except subprocess.TimeoutExpired as exc:
            host_timed_out = True
            qemu_err = (exc.stderr or b"").decode(errors="replace")
        duration = time.monotonic() - start

        rc_text = _read_text(job / "rc").strip()
        guest_timed_out = (job / "timed_out").exists()
        returncode = int(rc_text) if rc_text.lstrip("-").isdigit() else None
        if guest_timed_out:
            returncode = -9
        stderr = _read_text(job / "stderr")
        if returncode is None:
            stderr += (f"\n[guest.py] no exit status from the guest; qemu "
                       f"{'killed after ' + str(hard_limit_s) + ' s' if host_timed_out else 'exited'}"
                       f"{': ' + qemu_err.strip() if qemu_err.strip() else ''}\n")
        outputs = {str(p.relative_to(job / "out")): _read_text(p)
                   for p in sorted((job / "out").rglob("*")) if p.is_file()}
        if out_dir is not None:
            shutil.copytree(job / "out", out_dir, dirs_exist_ok=True, symlinks=True)
        return GuestResult(
            outputs=outputs, args=command, returncode=returncode, stdout=_read_text(job / "stdout"),
            stderr=stderr, timed_out=guest_timed_out or host_timed_out,
            init_log=_read_text(job / "init.log"), console=_read_text(console),
            duration_s=duration)


def substitute_out(command):
    """``command`` (a sequence) with "{out}" in each argument replaced by the guest's
    $FFTUNE_VM_OUT path."""
    return [str(a).replace("{out}", DEFAULT_GUEST_ENV["FFTUNE_VM_OUT"]) for a in command]


def _main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="tests/vm/guest.py", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    sub.add_parser("check", help="say whether the guest can run here, and why not")
    build = sub.add_parser("build", help="build (or reuse) the cached initramfs")
    build.add_argument("--force", action="store_true")
    run = sub.add_parser("run", help="run COMMAND in the guest; exits with its status")
    run.add_argument("--cwd")
    run.add_argument("--env", action="append", default=[], metavar="KEY=VALUE")
    run.add_argument("--timeout", type=float, default=300.0, help="seconds (default 300)")
    run.add_argument("--verbose", action="store_true", help="also print init.log and console")
    run.add_argument("--out", metavar="DIR",
                     help="bring back what the command writes under $FFTUNE_VM_OUT into DIR "
                          "('{out}' in the command stands for that path in the guest)")
    run.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)

    if args.cmd == "check":
        ok, reason = guest_available()
        print(("available: " if ok else "unavailable: ") + reason)
        return 0 if ok else 1
    try:
        if args.cmd == "build":
            kernel = find_kernel()
            print(build_initramfs(kernel, force=args.force))
            print(boot_image(kernel))
            return 0
        command = args.command[1:] if args.command[:1] == ["--"] else args.command
        if not command:
            parser.error("run: no command given")
        env = {}
        for item in args.env:
            key, sep, value = item.partition("=")
            if not sep:
                parser.error(f"--env {item!r}: expected KEY=VALUE")
            env[key] = value
        if args.out:
            if os.path.exists(args.out) and not os.path.isdir(args.out):
                parser.error(f"--out {args.out}: not a directory")
            command = substitute_out(command)
        result = run_in_guest(command, env=env, cwd=args.cwd, timeout_s=args.timeout, out_dir=args.out)
    except GuestUnavailable as exc:
        print(f"guest.py: error: {exc}", file=sys.stderr)
        return 2
    sys.stdout.write(result.stdout)
    sys.stderr.write(result.stderr)
    if args.verbose:
        sys.stderr.write(f"--- init.log\n{result.init_log}--- console\n{result.console}")
    print(f"[guest.py] returncode {result.returncode}, {result.duration_s:.1f} s"
          f"{', TIMED OUT' if result.timed_out else ''}"
          + (f"; {len(result.outputs)} files back in {args.out}" if args.out else ""), file=sys.stderr)
    return result.returncode if result.returncode is not None and result.returncode >= 0 else 1


if __name__ == "__main__":
    sys.exit(_main())
