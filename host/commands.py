"""Subcommands ``fftune detect | quantify | tune | run | import-canlog | export``."""
import os
import sys

from fftune.analysis.errors import FftuneError
from fftune.host.config import check_output_dir, load_config
from fftune.host.drive import BusOptions, DriveClient, add_bus_arguments, int_in_range
from fftune.host.resources import config_path

DEFAULT_CONFIG = config_path("demo.yaml")

_HELP = {
    "detect": "random odd multisines at several levels: BLA, nonlinear and noise levels, odd/even verdict",
    "quantify": "HOSIDFs vs frequency and amplitude from sine experiments",
    "tune": "tune the Coulomb feed-forward K_fc (sweep + automated search), then K_v",
    "run": "detect, quantify and tune in order",
}


def _common(p):
    p.add_argument("--config", default=DEFAULT_CONFIG,
                   help="experiment configuration YAML (default: configs/demo.yaml)")
    p.add_argument("--out", default=None, help="output directory (default: the configuration's 'output')")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")


def add_parser(sub):
    for name in ("detect", "quantify", "tune", "run"):
        p = sub.add_parser(name, help=_HELP[name], description=_HELP[name] + ".")
        _common(p)
        p.add_argument("--machine", default=None, metavar="FILE",
                       help="a machine file (configs/machine_demo.yaml): every axis on the bus "
                            "at once, one thread each (docs/machine.md)")
        p.add_argument("--dry-run", action="store_true",
                       help="connect, check the plan against the drive's limits and the "
                            "configuration's (limits:), print it; nothing moves, nothing is written")
        add_bus_arguments(p)
        p.set_defaults(func=_experiment, steps=("detect", "quantify", "tune") if name == "run" else (name,))

    p = sub.add_parser("plan", help="check and print the plan of a configuration (nothing moves)",
                       description="Every excitation of the configuration's steps (levels, "
                                   "amplitudes, velocities, frequencies, bands, periods, "
                                   "capacities) against the drive's limits read from the drive "
                                   "and the configuration's limits: section. Without a drive "
                                   "(unreachable, or --offline) what the configuration alone "
                                   "allows is checked and the rest is named as not checked. "
                                   "Exit 2 with one error line on a violation.")
    p.add_argument("--config", default=DEFAULT_CONFIG,
                   help="experiment configuration YAML (default: configs/demo.yaml)")
    p.add_argument("--steps", default="detect,quantify,tune",
                   help="experiments to plan (comma separated; default all)")
    p.add_argument("--offline", action="store_true", help="do not contact a drive")
    add_bus_arguments(p)
    p.set_defaults(func=_plan)

    p = sub.add_parser("import-canlog", help="analyse a CAN log of a session with the drive",
                       description="Decode a CAN traffic log (python-can formats: candump .log, "
                                   ".asc, .blf, .trc, ...), reassemble the SDO transfers of parameter "
                                   "writes and recorder uploads into run records, write them as "
                                   "captures and analyse them as the live session did.")
    p.add_argument("file", help="CAN log file")
    p.add_argument("--eds", default=None, help="the drive's EDS (default: the firmware_sim build's)")
    p.add_argument("--node-id", type=int_in_range("node id", 1, 127), default=None,
                   help="drive node id 1 .. 127 (default: config, else 1)")
    p.add_argument("--steps", default="detect,quantify,tune",
                   help="experiments the session ran (comma separated; default all)")
    _common(p)
    p.set_defaults(func=_import_canlog)

    p = sub.add_parser("export", help="export capture files to .mat or CSV",
                       description="Write each capture (HDF5) of a directory as MATLAB .mat "
                                   "or CSV (one file per run, signals as columns).")
    p.add_argument("captures", help="a capture file or a directory of them")
    p.add_argument("--format", choices=("mat", "csv"), default="mat")
    p.add_argument("--to", default=None, help="output directory (default: beside the captures)")
    p.add_argument("--bla", action="store_true",
                   help="instead: the detect step's BLA with its variances, one .mat per level "
                        "(MATLAB frd/idfrd and FdiTools layouts; docs/capture-format.md)")
    p.set_defaults(func=_export)


def _prepare(args):
    cfg = load_config(args.config)
    out = check_output_dir(args.out or cfg["output"], create=False)
    return cfg, out


def _parse_steps(text):
    steps = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in steps if s not in ("detect", "quantify", "tune")]
    if bad or not steps:
        raise FftuneError(f"--steps: unknown experiment {bad[0] if bad else text!r} (detect, quantify, tune)")
    return steps


def _client(args, cfg):
    d = cfg["drive"]
    return DriveClient(BusOptions.from_args(args, d), sdo_timeout_s=d["sdo_timeout_s"],
                       sdo_retries=d["sdo_retries"], heartbeat_ms=d["heartbeat_ms"],
                       host_node_id=d["host_node_id"], run_timeout_s=d["run_timeout_s"],
                       progress=not getattr(args, "no_progress", False))


def _experiment(args):
    from fftune.host.pipeline import check_plan, run_pipeline, summary_lines
    from fftune.host.plan import preflight

    if getattr(args, "machine", None):
        from fftune.host.machine import run_cli
        return run_cli(args)
    cfg = load_config(args.config)
    # what the configuration alone tells (its limits:, drive.fs_hz, controller.u_max): refused
    # before the drive is contacted
    preflight(cfg, steps=args.steps)
    # The client checks the EDS (file, drive profile) before anything is written. The output
    # directory is proven writable here and made with the first capture: a session that
    # fails before its first experiment (unreachable drive, refused plan) leaves none.
    client = _client(args, cfg)
    out = check_output_dir(args.out or cfg["output"], create=False)
    with client:
        checked = check_plan(client, cfg, args.steps)   # the drive's limits: before enabling
        if args.dry_run:
            print("\n".join(checked.lines(args.config)))
            print("fftune: dry run: the drive was not enabled, no run started, no file written")
            return 0
        client.enable()
        results = run_pipeline(client, cfg, out, steps=args.steps, figures=not args.no_figures,
                               log=lambda s: print(s, flush=True))
    print("\n".join(summary_lines(results, out)))
    return 0


def _plan(args):
    from fftune.host.pipeline import check_plan
    from fftune.host.plan import preflight

    cfg = load_config(args.config)
    steps = _parse_steps(args.steps)
    checked = preflight(cfg, steps=steps)
    if args.offline:
        checked.notes.append("--offline: checked against the configuration only; run "
                             "`fftune plan` with the drive reachable to check its limits")
    else:
        client = _client(args, cfg)         # (options and the EDS: errors, not "no drive")
        try:
            client.connect()
        except FftuneError as exc:
            checked.notes.append(f"no drive reached ({exc}): checked against the configuration "
                                 f"only")
        else:
            with client:
                checked = check_plan(client, cfg, steps)
    print("\n".join(checked.lines(args.config)))
    return 0


def _import_canlog(args):
    from fftune.host.canlog import ReplayDrive, read_transfers, session_from_transfers
    from fftune.host.odmap import DEFAULT_EDS
    from fftune.host.pipeline import run_pipeline, summary_lines

    cfg, out = _prepare(args)
    node_id = args.node_id or cfg["drive"]["node_id"]
    eds = args.eds or cfg["drive"]["eds"] or DEFAULT_EDS
    transfers = read_transfers(args.file, node_id)
    sess = session_from_transfers(transfers, eds, node_id)
    if not sess.runs:
        n_stats = sum(1 for tr in transfers if tr.direction == "upload" and tr.index in (0x2041, 0x2043))
        raise FftuneError(f"{args.file}: no complete run (start command + recorder upload) of node "
                          f"{node_id} in the log ({len(transfers)} SDO transfers"
                          + (f"; {n_stats} uploads of the drive's statistics 0x2041/0x2043: a "
                             f"session on statistics cannot be replayed, its results.yaml holds "
                             f"the analysis; log with capture: raw or both" if n_stats else "") + ")")
    # the log holds recordings: every step replays raw samples (the drive's statistics of a
    # logged session are not re-derived from frames)
    for step in ("detect", "quantify", "tune"):
        cfg[step]["capture"] = "raw"
    print(f"{args.file}: {len(transfers)} SDO transfers, {len(sess.runs)} runs of node {node_id}")
    steps = _parse_steps(args.steps)
    results = run_pipeline(ReplayDrive(sess, args.file), cfg, out, steps=steps,
                           figures=not args.no_figures, log=lambda s: print(s, flush=True),
                           preflight=False)
    results_note = f"analysed from CAN log {args.file}"
    print(results_note)
    print("\n".join(summary_lines(results, out)))
    return 0


def _export(args):
    from fftune.host.captures import export_captures
    if args.bla:
        from fftune.host.bla_export import export_bla
        if args.format != "mat":
            raise FftuneError("--bla writes .mat only (--format mat)")
        files = export_bla(args.captures, args.to)
    else:
        files = export_captures(args.captures, args.format, args.to)
    for f in files:
        print(f)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(0)
