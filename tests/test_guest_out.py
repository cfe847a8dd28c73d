"""tests/vm/guest.py run --out DIR: the command's "{out}" is the guest's $FFTUNE_VM_OUT and
what it writes there comes back into DIR, binary (no qemu booted here: run_in_guest is
stood in for by a double that writes into the job's out directory as the guest would)."""
import os

import yaml

import vmguest
from fftune.host.config import validate

guest = vmguest._guest


def test_out_is_substituted_and_files_come_back_binary(tmp_path, monkeypatch, capsys):
    seen = {}
    png = b"\x89PNG\r\n\x1a\n\x00\xff\xfe binary"

    def fake_run(command, env=None, cwd=None, timeout_s=300.0, out_dir=None, **kw):
        seen.update(command=command, out_dir=out_dir)
        job_out = tmp_path / "job-out"            # what the guest left in $FFTUNE_VM_OUT
        (job_out / "demo").mkdir(parents=True)
        (job_out / "demo" / "figure.png").write_bytes(png)
        (job_out / "demo" / "results.yaml").write_text("a: 1\n")
        guest.shutil.copytree(job_out, out_dir, dirs_exist_ok=True)
        return guest.GuestResult(args=command, returncode=0, stdout="done\n", stderr="",
                                 outputs={"demo/figure.png": "?", "demo/results.yaml": "a: 1\n"})
    monkeypatch.setattr(guest, "run_in_guest", fake_run)
    out = tmp_path / "back"
    rc = guest._main(["run", "--out", str(out), "--", "fftune", "demo", "--out", "{out}/demo"])
    assert rc == 0
    assert seen["command"] == ["fftune", "demo", "--out", "/run/vmjob/out/demo"]
    assert seen["out_dir"] == str(out)
    assert (out / "demo" / "figure.png").read_bytes() == png
    assert "2 files back in" in capsys.readouterr().err


def test_run_in_guest_copies_the_out_tree(tmp_path, monkeypatch):
    """The copy step of run_in_guest itself, with qemu stood in for by a script that writes
    into the job directory's out/ (the 9p share) as the guest does."""
    monkeypatch.setattr(guest, "find_qemu", lambda: "qemu")
    monkeypatch.setattr(guest, "find_kernel", lambda: "k")
    monkeypatch.setattr(guest, "build_initramfs", lambda k: "i")
    monkeypatch.setattr(guest, "boot_image", lambda k: "b")

    def fake_qemu(argv, **kw):
        job = next(a.split("path=")[1].split(",")[0] for a in argv if "id=job," in a)
        os.makedirs(os.path.join(job, "out", "sub"))
        with open(os.path.join(job, "out", "sub", "x.bin"), "wb") as fh:
            fh.write(bytes(range(256)))
        with open(os.path.join(job, "rc"), "w") as fh:
            fh.write("0\n")
        return guest.subprocess.CompletedProcess(argv, 0, b"", b"")
    monkeypatch.setattr(guest.subprocess, "run", fake_qemu)
    r = guest.run_in_guest(["true"], out_dir=tmp_path / "o")
    assert r.returncode == 0 and (tmp_path / "o" / "sub" / "x.bin").read_bytes() == bytes(range(256))


def test_the_guest_demo_configuration_is_valid_and_small():
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with open(os.path.join(root, "configs", "demo_vm.yaml")) as fh:
        small = validate(yaml.safe_load(fh), "demo_vm.yaml")
    with open(os.path.join(root, "configs", "demo.yaml")) as fh:
        full = validate(yaml.safe_load(fh), "demo.yaml")

    def runs(c):
        d, q, t = c["detect"], c["quantify"], c["tune"]
        return (len(d["rms_levels"]) * d["realizations"], len(q["frequencies_hz"]) * len(q["rms_levels"]) * q["repeats"],
                t["sweep"]["points"] + (t["viscous"]["max_experiments"] if t["viscous"]["enabled"] else 0))
    assert all(a <= b / 2 for a, b in zip(runs(small), runs(full)) if b)
    assert small["tune"]["capture"] == "stats" and small["sim"]["plant"] == full["sim"]["plant"]
