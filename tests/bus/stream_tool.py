"""Test publisher process for the live viewer: ``python -m tests.bus.stream_tool ENDPOINT
--seconds S``: one latched goal, then arm states at ``--state-hz`` and camera images at
``--image-hz`` for S seconds (the messages of :mod:`tests.bus.pub_tool`), after every publisher
has a matching subscriber. Prints a JSON line with what it published."""

from __future__ import annotations

import argparse
import json
import sys
import time

from services.bus.config import ServiceConfig, load_config
from services.bus.runtime import Service
from tests.bus.pub_tool import goal, image, state


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("endpoint")
    ap.add_argument("--seconds", type=float, default=3.0)
    ap.add_argument("--state-hz", type=float, default=500.0)
    ap.add_argument("--image-hz", type=float, default=30.0)
    ap.add_argument("--image-bytes", type=int, default=20_000)
    args = ap.parse_args(argv)
    cfg = load_config(ServiceConfig, env={}, overrides={
        "zenoh.connect": [args.endpoint], "zenoh.multicast": False})
    svc = Service("streamtool", cfg).start()
    k = svc.keys
    state_pub, image_pub = svc.publisher(k.arm_state), svc.publisher(k.camera_image("cam0"))
    goal_pub = svc.publisher(k.goal("person"))
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline and not (state_pub.has_subscribers and image_pub.has_subscribers):
        time.sleep(0.01)
    time.sleep(0.5)  # matching status can precede the route by a little
    goal_pub.put(goal(0))
    images = [image(i, args.image_bytes) for i in range(8)]
    t0 = time.monotonic()
    n_states = n_images = 0
    end = t0 + args.seconds
    next_state, next_image = t0, t0
    while True:
        now = time.monotonic()
        if now >= end:
            break
        if now >= next_state:
            state_pub.put(state(n_states))
            n_states += 1
            next_state = t0 + n_states / args.state_hz
        if now >= next_image:
            image_pub.put(images[n_images % len(images)])
            n_images += 1
            next_image = t0 + n_images / args.image_hz
        time.sleep(max(0.0, min(next_state, next_image, end) - time.monotonic()))
    print(json.dumps({"states": n_states, "images": n_images, "goals": 1,
                      "seconds": time.monotonic() - t0}), flush=True)
    time.sleep(0.3)
    svc.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
