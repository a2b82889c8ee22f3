"""Test publisher process: ``python -m tests.bus.pub_tool ENDPOINT --states N ...``.

Publishes deterministic typed messages (see :func:`state`, :func:`goal`, :func:`image`) through
the project runtime after every publisher has a matching subscriber, then prints a JSON line
with what it published.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from services.bus.config import ServiceConfig, load_config
from services.bus.messages import ArmState, CompressedImage, Goal, vec3
from services.bus.runtime import Service


def state(i: int) -> ArmState:
    """The i-th arm state."""
    return ArmState(stamp_ns=1_000_000 + i * 2_000_000, tick=i, sim_time_ns=i * 2_000_000,
                    q=[0.001 * i] * 7, dq=[0.1] * 7, ee_position=vec3(0.3, 0.0, 0.4),
                    frame_id="base")


def goal(i: int) -> Goal:
    """The i-th goal."""
    return Goal(stamp_ns=5 + i, seq=i, name="person", valid=True, position=vec3(0.5, 0.0, 0.1 * i))


def image(i: int, size: int = 40_000) -> CompressedImage:
    """The i-th (fake JPEG) image of ``size`` bytes."""
    img = CompressedImage(frame_id="cam0", format="jpeg",
                          data=bytes((i * 7 + j) % 251 for j in range(size)))
    img.timestamp.seconds = 100 + i
    return img


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoint")
    ap.add_argument("--states", type=int, default=0)
    ap.add_argument("--goals", type=int, default=0)
    ap.add_argument("--images", type=int, default=0)
    ap.add_argument("--rate", type=float, default=0.0, help="states per second (0 = max)")
    ap.add_argument("--linger", type=float, default=0.5)
    args = ap.parse_args(argv)
    cfg = load_config(ServiceConfig, env={}, overrides={
        "zenoh.connect": [args.endpoint], "zenoh.multicast": False})
    svc = Service("pubtool", cfg).start()
    k = svc.keys
    pubs = {"state": svc.publisher(k.arm_state), "goal": svc.publisher(k.goal("person")),
            "image": svc.publisher(k.camera_image("cam0"))}
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and not all(
            p.has_subscribers for p in pubs.values() if p.has_subscribers is not None):
        time.sleep(0.01)
    time.sleep(0.5)  # matching status can precede the route by a little
    t0 = time.monotonic()
    for i in range(args.goals):
        pubs["goal"].put(goal(i))
    for i in range(args.images):
        pubs["image"].put(image(i))
    for i in range(args.states):
        pubs["state"].put(state(i))
        if args.rate > 0:
            due = t0 + (i + 1) / args.rate
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    print(json.dumps({"states": args.states, "goals": args.goals, "images": args.images,
                      "seconds": time.monotonic() - t0}), flush=True)
    time.sleep(args.linger)
    svc.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
