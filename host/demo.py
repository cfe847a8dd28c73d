"""``fftune demo``: the main job on the simulated drive (``make demo``)."""
import os
import subprocess
import sys


def add_parser(sub):
    p = sub.add_parser("demo", help="run the main job on the simulated drive")
    p.set_defaults(func=run)


def run(args):
    here = os.path.dirname(os.path.abspath(__file__))
    eds = os.path.join(here, "..", "firmware_sim", "build", "gen", "od_params.h")
    print("fftune demo: the pipeline is being assembled; present pieces:")
    print(f"  object dictionary generated: {os.path.exists(eds)}")
    print(f"  python {sys.version.split()[0]}, fftune CLI ready")
    subprocess.run([sys.executable, "-c", "import analysis, host"], check=True)
    return 0
