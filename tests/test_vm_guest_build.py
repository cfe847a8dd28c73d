"""The guest's host side without booting it: module resolution, the initramfs cache, the job
script. Fast; the boot itself is tested by the other tests/test_vm_*.py."""
import os
import subprocess

import pytest

import vmguest

guest = vmguest._guest


def _modules_dir(tmp_path, dep_lines, builtin=()):
    (tmp_path / "modules.dep").write_text("\n".join(dep_lines) + "\n")
    (tmp_path / "modules.builtin").write_text("".join(f"{b}\n" for b in builtin))
    return tmp_path


def test_modules_come_after_their_dependencies_and_only_once(tmp_path):
    mdir = _modules_dir(tmp_path, [
        "kernel/fs/9p/9p.ko: kernel/net/9p/9pnet.ko kernel/fs/fscache/fscache.ko kernel/fs/netfs/netfs.ko",
        "kernel/net/9p/9pnet.ko:",
        "kernel/fs/fscache/fscache.ko: kernel/fs/netfs/netfs.ko",
        "kernel/fs/netfs/netfs.ko:",
        "kernel/net/can/can-raw.ko: kernel/net/can/can.ko",
        "kernel/net/can/can.ko:",
    ])
    order = guest._resolve_modules(mdir, ["9p", "can_raw", "can"])
    assert sorted(order) == sorted(set(order))
    assert len(order) == 6
    for module, deps in (("9p", ["9pnet", "fscache", "netfs"]), ("fscache", ["netfs"]),
                         ("can-raw", ["can"])):
        at = next(i for i, p in enumerate(order) if p.endswith(f"/{module}.ko"))
        for dep in deps:
            assert next(i for i, p in enumerate(order) if p.endswith(f"/{dep}.ko")) < at, order


def test_builtin_modules_are_skipped_and_missing_ones_named(tmp_path):
    mdir = _modules_dir(tmp_path, ["kernel/drivers/net/can/vcan.ko: kernel/drivers/net/can/dev/can-dev.ko"],
                        builtin=["kernel/drivers/net/can/dev/can-dev.ko"])
    assert guest._resolve_modules(mdir, ["vcan"]) == ["kernel/drivers/net/can/vcan.ko"]
    with pytest.raises(guest.GuestUnavailable, match="kernel module can_bcm"):
        guest._resolve_modules(mdir, ["can-bcm"])


def test_dependency_loop_is_reported(tmp_path):
    mdir = _modules_dir(tmp_path, ["a.ko: b.ko", "b.ko: a.ko"])
    with pytest.raises(guest.GuestUnavailable, match="dependency loop"):
        guest._resolve_modules(mdir, ["a"])


def test_job_script_passes_awkward_environment_values_and_arguments_unchanged(tmp_path):
    env = {"PLAIN": "x", "SPACES": "a b  c", "QUOTES": "it's \"quoted\" $HOME `x`",
           "NEWLINE": "one\ntwo"}
    script = guest._job_script(["/usr/bin/env"], env, str(tmp_path))
    (tmp_path / "job.sh").write_text(script)
    out = subprocess.run(["/usr/bin/env", "-i", "/bin/sh", str(tmp_path / "job.sh")],
                         capture_output=True, text=True, check=True).stdout
    for key, value in env.items():
        assert f"{key}={value}\n" in out, out
    argv_script = guest._job_script(["printf", "[%s]", "a b", "$x", "'"], {}, str(tmp_path))
    (tmp_path / "argv.sh").write_text(argv_script)
    out = subprocess.run(["/bin/sh", str(tmp_path / "argv.sh")], capture_output=True,
                         text=True, check=True).stdout
    assert out == "[a b][$x][']"


def test_job_script_fails_with_126_when_the_directory_is_missing(tmp_path):
    (tmp_path / "job.sh").write_text(guest._job_script("true", {}, str(tmp_path / "nowhere")))
    proc = subprocess.run(["/bin/sh", str(tmp_path / "job.sh")], capture_output=True)
    assert proc.returncode == 126


def test_bad_environment_name_is_refused():
    with pytest.raises(ValueError, match="not a shell identifier"):
        guest._job_script("true", {"A-B": "1"}, "/")


def test_initramfs_is_rebuilt_only_when_an_input_changes(tmp_path, monkeypatch):
    ok, reason = guest_parts_available()
    if not ok:
        pytest.skip(reason)
    init = tmp_path / "guest_init.sh"
    init.write_text(guest.GUEST_INIT.read_text())
    monkeypatch.setattr(guest, "GUEST_INIT", init)
    cache = tmp_path / "cache"
    first = guest.build_initramfs(cache_dir=cache)
    stamp = first.stat().st_mtime_ns
    os.utime(first, ns=(stamp - 10**9, stamp - 10**9))  # so a rewrite would show
    assert guest.build_initramfs(cache_dir=cache).stat().st_mtime_ns == stamp - 10**9
    init.write_text(init.read_text() + "\n# changed\n")
    assert guest.build_initramfs(cache_dir=cache).stat().st_mtime_ns != stamp - 10**9
    listing = subprocess.run(["cpio", "-it", "--quiet"], stdin=open(first, "rb"),
                             capture_output=True, text=True, check=True).stdout.split()
    for name in ("init", "bin/busybox", "modules.load", "lib/modules/vcan.ko",
                 "lib/modules/can_raw.ko", "lib/modules/9pnet_virtio.ko"):
        assert name in listing, listing


def test_pvh_note_is_found_in_the_kernel_image_only():
    ok, reason = guest_parts_available()
    if not ok:
        pytest.skip(reason)
    kernel = guest.find_kernel()
    image = guest.boot_image(kernel)
    if image == kernel.vmlinuz:
        pytest.skip(f"{kernel.vmlinuz} has no extractable vmlinux with a PVH note")
    assert guest._has_pvh_entry(image.read_bytes())
    assert not guest._has_pvh_entry(guest.find_busybox().read_bytes())


def guest_parts_available():
    try:
        guest.find_kernel()
        guest.find_busybox()
        guest.find_cpio()
    except guest.GuestUnavailable as exc:
        return False, f"SocketCAN guest parts missing: {exc}"
    return True, ""
