"""``fftune demo`` (``make demo``): the whole pipeline against the simulated drive.

Starts ``drive_sim`` on a free loopback socketcand port (or on the bus the options name:
``-i socketcan -c vcan0``, ``-i socketcand --host H --port P``; ``--bitrate B`` or the
configuration's ``sim.bitrate``: behind a simulated CAN bus of B bit/s), runs detect ->
quantify -> tune with ``configs/demo.yaml`` through the CANopen client exactly as ``fftune
run`` does, stops the drive (also on an error or Ctrl-C) and leaves everything in
``out/demo/``.
"""
import os
import time

from fftune.analysis.errors import FftuneError
from fftune.host.commands import DEFAULT_CONFIG
from fftune.host.config import load_config, output_session
from fftune.host.drive import DriveClient, add_bus_arguments
from fftune.host.fmu import is_fmu_plant, overrides_note
from fftune.host.sim import DEFAULT_PLANT, check_bus, derived_plant, start_drive_sim


def add_parser(sub):
    p = sub.add_parser("demo", help="run detect, quantify and tune on the simulated drive (make demo)",
                       description="Start drive_sim on a free loopback port, run the pipeline "
                                   "(`fftune run`) against it, stop it, and leave results.yaml, "
                                   "captures, figures and report.html in the output directory.")
    p.add_argument("--config", default=DEFAULT_CONFIG, help="configuration (default configs/demo.yaml)")
    p.add_argument("--plant", default=None,
                   help="plant of the simulated drive (default: the configuration's sim.plant, "
                        "else configs/plant_twomass.yaml)")
    p.add_argument("--out", default=None, help="output directory (default: the configuration's); "
                   "an earlier one is kept as <out>.previous")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--machine", default=None, metavar="FILE",
                   help="a machine file (configs/machine_demo.yaml): one drive_sim serving every "
                        "axis' node on one bus, all axes tuned at once (docs/machine.md)")
    p.add_argument("--realtime", action="store_true",
                   help="the simulated drive steps at its controller rate (default: as fast as it can)")
    add_bus_arguments(p, drive_side=True, port_default=0)
    p.set_defaults(func=run)


def resolve_plant(cfg, plant=None):
    """The simulated drive's plant file: ``plant``, else the configuration's ``sim.plant``,
    else configs/plant_twomass.yaml ("configs/NAME" of the shipped files found from anywhere)."""
    plant = plant or cfg["sim"]["plant"] or DEFAULT_PLANT
    if not os.path.isabs(plant) and not os.path.exists(plant):
        from fftune.host.resources import config_path
        packaged = config_path(os.path.basename(plant))
        if os.path.dirname(plant) == "configs" and os.path.exists(packaged):
            plant = packaged
    return plant


def run(args):
    from fftune.host.pipeline import summary_lines
    from fftune.host.plan import preflight

    t0 = time.monotonic()
    # the demo starts its own drive on a free port: python-can's configuration plays no part
    args.interface = args.interface or "socketcand"
    if args.machine:
        from fftune.host.machine import demo_cli
        return demo_cli(args)
    cfg = load_config(args.config)
    bitrate = args.bitrate if args.bitrate is not None else cfg["sim"]["bitrate"]
    cfg["sim"]["bitrate"] = bitrate  # the steps' default capture follows it (Session.capture_mode)
    check_bus(args.interface, args.channel, bitrate)  # before anything is moved or written
    if args.interface == "socketcan":
        from fftune.analysis.errors import FftuneError
        from fftune.host.socketcan_check import socketcan_problem
        problem = socketcan_problem(args.channel)
        if problem:
            raise FftuneError(f"-i socketcan -c {args.channel}: {problem}")
    preflight(cfg)                                    # what the configuration alone tells
    # a fresh run (an earlier directory kept as <out>.previous); failed before its first
    # experiment: nothing left behind (not even a parent folder it made), the earlier one back
    kept = []
    with output_session(args.out or cfg["output"], set_aside=True, log=kept.append) as out:
        results = _run(args, cfg, out, bitrate)
    for line in kept:
        print(f"fftune demo: {line}")
    print("\n".join(summary_lines(results, out)))
    print(_clock_note(results, args.realtime))
    print(f"fftune demo: done in {time.monotonic() - t0:.1f} s; open {os.path.relpath(out)}/report.html")
    return 0


def _clock_note(results, realtime):
    """What the time budget's columns are: excitation on the drive's (simulated) clock,
    the rest on the host's wall clock."""
    total = (results.get("time_budget_s") or {}).get("total") or {}
    exc = total.get("excitation")
    if exc is None:
        return "  (no time budget)"
    if realtime:
        return (f"  (excitation: the drive's clock, here real time (--realtime); bus, host and "
                f"wall: the host's clock)")
    return (f"  (excitation: simulated time; drive_sim free-runs faster than real time, a real "
            f"drive needs the {exc:.0f} s of excitation plus the bus time; bus, host, wall: real time)")


def _run(args, cfg, out, bitrate):
    from fftune.host.pipeline import check_plan, run_pipeline

    d = cfg["drive"]
    plant = resolve_plant(cfg, args.plant)
    shown = os.path.relpath(plant)
    where = f"{args.config}: key 'sim.overrides'"
    if cfg["sim"]["overrides"] and is_fmu_plant(plant):
        print(f"fftune demo: {overrides_note(plant, where)}", flush=True)
    elif cfg["sim"]["overrides"]:
        plant = derived_plant(plant, cfg["sim"]["overrides"], os.path.join(out, "plant.yaml"), where=where)
        shown += " with sim.overrides -> " + os.path.relpath(plant)
    node_id = args.node_id if args.node_id is not None else d["node_id"]
    sim = start_drive_sim(plant, host=args.host, port=args.port, node_id=node_id,
                          log_path=os.path.join(out, "drive_sim.log"), interface=args.interface,
                          channel=args.channel, bitrate=bitrate, realtime=args.realtime)
    try:
        bus = f", CAN bus model {bitrate} bit/s" if bitrate else ""
        print(f"fftune demo: drive_sim ({shown}) listening on {sim.describe()}{bus}", flush=True)
        opts = sim.bus_options(node_id, d["eds"] or None)
        client = DriveClient(opts, sdo_timeout_s=d["sdo_timeout_s"], sdo_retries=d["sdo_retries"],
                             heartbeat_ms=d["heartbeat_ms"], host_node_id=d["host_node_id"],
                             run_timeout_s=d["run_timeout_s"], progress=not args.no_progress)
        with client:
            check_plan(client, cfg)          # the drive's limits, before it is enabled
            client.enable()
            return run_pipeline(client, cfg, out, log=lambda s: print(s, flush=True))
    except FftuneError as exc:
        said = sim.reported_error()          # the simulator's own reason (an FMU plant's failed step)
        if said:
            raise FftuneError(f"{exc}; drive_sim: {said}") from None
        raise
    finally:
        sim.stop()
