"""Write ``tests/data/planner_replay.mcap``: the start of a lockstep feeding run through real
processes on loopback (router, ``psm arm --clock lockstep --max-ticks N``, ``psm plan``,
``psm record`` of the arm's state and command keys), for the planner's replay test.

Run ``python scripts/make_planner_replay.py [--ticks 800]``. Deterministic in content: the
lockstep arm and the planner compute the same states and commands on every run.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.supervisor import ManagedProcess, free_port, psm_argv  # noqa: E402

OUT = ROOT / "tests" / "data" / "planner_replay.mcap"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=800, help="arm ticks to record (2 ms each)")
    ap.add_argument("-o", "--out", type=Path, default=OUT)
    args = ap.parse_args()
    port = free_port()
    bus = ["--connect", f"tcp/127.0.0.1:{port}", "--no-multicast", "--mode", "client"]
    procs: list[ManagedProcess] = []
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp)

        def start(name: str, argv: list[str]) -> ManagedProcess:
            p = ManagedProcess(name, psm_argv(argv), log / f"{name}.log", cwd=ROOT)
            procs.append(p)
            return p

        try:
            start("router", ["serve", "router", "--listen", f"tcp/127.0.0.1:{port}"])
            time.sleep(1.0)
            rec = start(
                "recorder",
                [
                    "record",
                    *bus,
                    "-o",
                    str(args.out),
                    "--overwrite",
                    "-k",
                    "psm/arm/state",
                    "-k",
                    "psm/arm/command",
                ],
            )
            time.sleep(1.5)
            arm = start("arm", ["arm", *bus, "--clock", "lockstep", "--max-ticks", str(args.ticks)])
            start("planner", ["plan", *bus, "--set", f'planner.cache_dir="{ROOT / "out" / "models"}"'])
            if arm.wait(120) is None:
                raise SystemExit("the arm did not finish in 120 s:\n" + arm.log_tail())
            time.sleep(0.5)
            rec.stop()
        finally:
            for p in reversed(procs):
                p.stop()
    print(f"wrote {args.out} ({args.out.stat().st_size // 1024} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
