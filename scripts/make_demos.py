"""Regenerate the demonstrations under ``data/demos/`` (deterministic: same bytes every run).

    python scripts/make_demos.py            # write data/demos/*.mcap and data/demos/README.md
    python scripts/make_demos.py --check    # regenerate in a temp dir and compare with the files

Each demonstration (:func:`services.arm.demos.build_demos`, on the scene of
``configs/feeding.toml``) is a simulated kinesthetic teaching session of the Franka Panda: the
arm is guided along a minimum-jerk path through the task's via-points with seeded human-like
tremor and every state is recorded at 500 Hz (values rounded to 2**-20 so the files compress;
see ``docs/arm.md``).
"""

from __future__ import annotations

import argparse
import filecmp
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from services.arm.demos import build_demos  # noqa: E402
from services.arm.teach import (  # noqa: E402
    TeachConfig,
    teach,
    write_teach_mcap,
)
from services.robot.model import RobotModel  # noqa: E402
from services.robot.recordings import ee_trajectory  # noqa: E402
from services.tasks.feeding import load_feeding  # noqa: E402

QUANTIZE_BITS = 20


def generate(out_dir: Path, names: list[str] | None = None, scene: Path | None = None) -> list[Path]:
    """Write the demonstrations (all, or ``names``) and the README into ``out_dir``, for the
    feeding config ``scene`` (default ``configs/feeding.toml``)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    feeding = load_feeding(scene)
    robot = RobotModel.load()
    written = []
    rows = []
    for name, spec in build_demos(feeding.scene).items():
        if names and name not in names:
            continue
        snaps = teach(robot, spec.path(), TeachConfig(tremor=spec.tremor()))
        path = write_teach_mcap(
            out_dir / f"{name}.mcap",
            robot,
            snaps,
            metadata={
                "task": name,
                "description": spec.description,
                "goal": list(spec.goal),
                "points": [list(p) for p in spec.points],
                "durations": list(spec.durations),
                "velocities": None if spec.velocities is None else [list(v) for v in spec.velocities],
                "tremor_seed": spec.seed,
            },
            quantize_bits=QUANTIZE_BITS,
        )
        written.append(path)
        t, X = ee_trajectory(path, robot)
        V = (X[2:] - X[:-2]) / (t[2:] - t[:-2])[:, None]
        rows.append(
            f"| `{name}.mcap` | {spec.description} | "
            f"({', '.join(f'{c:.2f}' for c in spec.points[0])}) | "
            f"({', '.join(f'{c:.2f}' for c in spec.goal)}) | {t[-1]:.2f} | "
            f"{abs(V).max(axis=0)[1]:.2f} | {float(abs(V).max()):.2f} | "
            f"{path.stat().st_size / 1024:.0f} |"
        )
    if names is None:
        readme = out_dir / "README.md"
        readme.write_text(
            "# Demonstrations\n\n"
            "Simulated kinesthetic demonstrations of the Franka Panda (paper §IV): the five "
            "feeding sub-tasks, in order "
            + ", ".join(f"`{n}`" for n in feeding.task.sequence)
            + ", and the cylinder-rolling strike. Regenerate with "
            "`python scripts/make_demos.py` (deterministic); the scene is "
            "`configs/feeding.toml`, the via-points are in `services/arm/demos.py`, the format "
            "in `docs/arm.md`.\n\n"
            "Each file holds `psm/arm/state` (`psm.ArmState`) at 500 Hz and "
            "`psm/arm/transforms` (`foxglove.FrameTransforms`) at 10 Hz, log time = sim time, "
            "plus a `psm.teach` metadata record (task, via-points, durations, seed). Values are "
            "rounded to 2^-20 (about 1 µrad / 1 µm). Positions are metres in the robot base "
            "frame (table top z = 0, x forward, y left); the hand points down throughout.\n\n"
            "| file | motion | start (m) | goal (m) | duration (s) | max abs v_y (m/s) | "
            "max abs v (m/s, any axis) | size (KiB) |\n"
            "|---|---|---|---|---|---|---|---|\n" + "\n".join(rows) + "\n\n"
            "Learn one with `psm learn data/demos/reach_bowl.mcap` (the end-effector path is "
            "recomputed from the joint states by forward kinematics).\n"
        )
        written.append(readme)
    return written


def main(argv: list[str] | None = None) -> int:
    """Command line entry point; returns the exit code."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "data" / "demos")
    parser.add_argument(
        "--scene", type=Path, default=None, help="feeding config (default configs/feeding.toml)"
    )
    parser.add_argument(
        "--check", action="store_true", help="regenerate in a temp dir and compare with --out"
    )
    args = parser.parse_args(argv)
    if not args.check:
        for p in generate(args.out, scene=args.scene):
            print(f"wrote {p} ({p.stat().st_size / 1024:.0f} KiB)")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        fresh = generate(Path(tmp), scene=args.scene)
        bad = [p.name for p in fresh if not filecmp.cmp(p, args.out / p.name, shallow=False)]
    if bad:
        print(f"out of date: {', '.join(bad)}", file=sys.stderr)
        return 1
    print("demonstrations up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
