"""``psm arm`` (the simulated arm service), ``psm arm probe`` (a trivial controller for it) and
``psm teach`` (record a guided demonstration).

The argument definitions live here (light imports, so ``psm --help`` stays fast); the work is in
:mod:`services.arm.service`, :mod:`services.arm.probe` and :mod:`services.arm.teach`.
"""

from __future__ import annotations

import argparse
import textwrap
from typing import Any

#: The probe's patterns and what each commands (computed from the state only, so a lockstep
#: run is deterministic).
PROBE_PATTERNS: dict[str, str] = {
    "hold": "PD to the first state's EE position and orientation",
    "accel": "constant EE linear acceleration --accel (m/s²), orientation held",
    "sine": "PD tracking of x0 + A sin(2π f t) along y (A = --amplitude m, f = --frequency Hz, "
    "t = the arm's sim time since the first state)",
    "joint": "constant joint accelerations --joint-accel (rad/s²)",
    "bad": "cycles through invalid commands (NaN, inf, out of range, wrong sizes, unspecified "
    "mode, zero quaternion, undecodable bytes): none of them may move the arm",
}

PROBE_DESCRIPTION = "\n\n".join(
    (
        textwrap.fill(
            "A trivial controller for the arm: answers every <prefix>/arm/state with an "
            "<prefix>/arm/command at once (integration tests, benchmarks, poking a running arm).",
            88,
        ),
        "patterns:\n"
        + "\n".join(
            textwrap.fill(text, 88, initial_indent=f"  {name:7s}", subsequent_indent=" " * 9)
            for name, text in PROBE_PATTERNS.items()
        ),
        textwrap.fill(
            "The reply is computed and published on Zenoh's receive thread. --stop-after-tick N "
            "stops answering from tick N on (the process stays up, like a hung planner). Runs "
            "until SIGINT/SIGTERM or --max-runtime.",
            88,
        ),
    )
)


def _floats(text: str) -> list[float]:
    """A comma-separated list of floats (``"0,0.8,0"``)."""
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def add_probe_arguments(parser: argparse.ArgumentParser) -> None:
    """The probe's flags (for ``psm arm probe`` and ``python -m services.arm.probe``)."""
    from services.bus.config import add_config_arguments

    parser.add_argument("--pattern", choices=tuple(PROBE_PATTERNS), default="hold", help="default hold")
    parser.add_argument(
        "--accel", type=_floats, default=[0.0, 0.0, 0.0], metavar="AX,AY,AZ", help="m/s² (accel)"
    )
    parser.add_argument(
        "--joint-accel", type=_floats, default=[], metavar="A1,...", help="rad/s², one per joint (joint)"
    )
    parser.add_argument("--amplitude", type=float, default=0.05, metavar="M", help="sine amplitude, m")
    parser.add_argument("--frequency", type=float, default=0.5, metavar="HZ", help="sine frequency, Hz")
    parser.add_argument(
        "--stop-after-tick", type=int, default=-1, metavar="N", help="stop answering at tick N"
    )
    parser.add_argument("--max-runtime", type=float, default=0.0, metavar="S", help="exit after S seconds")
    parser.add_argument("--name", default="probe", help="service name (liveliness/status)")
    parser.add_argument(
        "--rt-priority", type=int, default=0, metavar="P", help="SCHED_FIFO priority 1-99 (0 = off)"
    )
    add_config_arguments(parser)


def register(subparsers: Any) -> None:
    """Add the ``arm`` (with its ``probe`` sub-command) and ``teach`` sub-commands."""
    from services.bus.config import add_config_arguments

    p = subparsers.add_parser(
        "arm",
        help="run the simulated arm (Pinocchio, Cartesian-acceleration interface)",
        description="Simulated arm: publishes <prefix>/arm/state every tick, applies "
        "<prefix>/arm/command (Cartesian acceleration + orientation reference, or joint "
        "accelerations), brakes when commands stop.",
    )
    add_config_arguments(p)
    p.add_argument("--clock", choices=("realtime", "lockstep"), help="clock mode")
    p.add_argument("--dt", type=float, metavar="S", help="control period, s (default 0.002)")
    p.add_argument("--urdf", help="robot URDF (default: Franka Panda)")
    p.add_argument("--ee-frame", help="end-effector frame name")
    p.add_argument("--start-pose", help="named start pose (ready, home, neutral, middle)")
    p.add_argument("--max-ticks", type=int, metavar="N", help="stop after N ticks")
    p.add_argument("--stats-file", metavar="FILE.json", help="write loop statistics at exit")
    p.add_argument(
        "--rt-priority",
        type=int,
        metavar="P",
        help="SCHED_FIFO priority 1-99 (needs CAP_SYS_NICE; default 0 = off)",
    )
    p.set_defaults(func=_run_arm)
    sub = p.add_subparsers(
        dest="arm_command",
        metavar="[probe]",
        title="sub-command",
        description="without one, `psm arm` runs the arm; `psm arm probe --help` for the probe",
    )
    pr = sub.add_parser(
        "probe",
        help="a trivial controller that answers every arm state (flags after `probe`)",
        description=PROBE_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_probe_arguments(pr)
    pr.set_defaults(func=_run_probe, command="arm probe")

    t = subparsers.add_parser(
        "teach",
        help="simulate a kinesthetic demonstration and record it to MCAP (500 Hz)",
        description="The arm is guided along an end-effector path (minimum-jerk through "
        "via-points with human-like tremor, or a recorded path) and every state is written to "
        "MCAP with the bus's message types, like `psm record` would.",
    )
    src = t.add_mutually_exclusive_group(required=True)
    src.add_argument("--task", help="a built-in demonstration (see --list)")
    src.add_argument(
        "--path",
        metavar="FILE",
        help="via-points .json {points, durations[, velocities]} or recorded path .csv (t,x,y,z)",
    )
    src.add_argument("--list", action="store_true", help="list the built-in demonstrations")
    t.add_argument("-o", "--out", metavar="FILE.mcap", help="output recording")
    t.add_argument(
        "--scene",
        metavar="FILE.toml",
        help="feeding scene and task for --task/--list (default configs/feeding.toml)",
    )
    t.add_argument("--seed", type=int, help="tremor seed (default: the task's, or 0)")
    t.add_argument("--no-tremor", action="store_true", help="follow the path exactly")
    t.add_argument("--dt", type=float, default=0.002, metavar="S", help="period, s (0.002)")
    t.add_argument("--prefix", default="psm", help="key prefix of the recorded channels")
    t.add_argument(
        "--quantize-bits",
        type=int,
        default=20,
        metavar="B",
        help="round stored values to 2**-B (0 = exact doubles; default 20)",
    )
    t.set_defaults(func=_run_teach)


def _run_arm(args: argparse.Namespace) -> int:
    from services.arm.config import ArmConfig
    from services.arm.service import main
    from services.bus.config import config_from_args

    extra = {
        "clock": args.clock,
        "arm.dt_s": args.dt,
        "arm.urdf": args.urdf,
        "arm.ee_frame": args.ee_frame,
        "arm.start_pose": args.start_pose,
        "arm.max_ticks": args.max_ticks,
        "arm.stats_file": args.stats_file,
        "arm.rt_priority": args.rt_priority,
    }
    cfg = config_from_args(ArmConfig, args, extra)
    return main(cfg)


def _run_probe(args: argparse.Namespace) -> int:
    from services.arm.probe import run

    return run(args)


def _run_teach(args: argparse.Namespace) -> int:
    from services.arm.demos import load_demos
    from services.arm.teach import TeachConfig, Tremor, load_path_file, teach, write_teach_mcap
    from services.cli import CLIError
    from services.robot.model import RobotModel

    demos = load_demos(args.scene) if args.list or args.task else {}
    if args.list:
        for name, d in demos.items():
            print(f"{name:16s} goal {d.goal}  {d.description}")
        return 0
    if not args.out:
        raise CLIError("--out is required")
    if args.dt <= 0 or args.dt > 0.1:
        raise CLIError("--dt must be in (0, 0.1] s")
    meta: dict[str, Any] = {}
    if args.task:
        if args.task not in demos:
            raise CLIError(f"unknown task {args.task!r}; known: {', '.join(demos)}")
        spec = demos[args.task]
        path = spec.path()
        seed = spec.seed if args.seed is None else args.seed
        meta = {
            "task": spec.name,
            "description": spec.description,
            "goal": list(spec.goal),
            "points": [list(p) for p in spec.points],
            "durations": list(spec.durations),
        }
    else:
        path = load_path_file(args.path)
        seed = args.seed or 0
        meta = {"path_file": str(args.path)}
    tremor = None if args.no_tremor else Tremor(seed=seed)
    meta["tremor_seed"] = seed if tremor else None
    robot = RobotModel.load()
    snaps = teach(robot, path, TeachConfig(dt_ns=round(args.dt * 1e9), tremor=tremor))
    out = write_teach_mcap(
        args.out,
        robot,
        snaps,
        prefix=args.prefix,
        metadata=meta,
        quantize_bits=args.quantize_bits or None,
    )
    print(f"wrote {out} ({len(snaps)} states, {snaps[-1].time_ns * 1e-9:.2f} s)")
    return 0
