"""The committed replay fixture ``tests/data/bus_replay.mcap``: how it was made.

Regenerate with ``.venv/bin/python -m tests.bus.fixture_data`` (only if the catalogue changes;
the test compares the committed file against :func:`fixture_samples`).
"""

from __future__ import annotations

from pathlib import Path

from services.bus.messages import (
    ArmCommand,
    ArmState,
    CompressedImage,
    Goal,
    Keys,
    Obstacle,
    ObstacleSet,
    encode,
    quat,
    vec3,
)

PATH = Path(__file__).resolve().parents[1] / "data" / "bus_replay.mcap"
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 10_000_000  # 10 ms between arm ticks -> the fixture lasts 0.39 s


def fixture_samples() -> list[tuple[str, str, bytes, int]]:
    """``(key, encoding, payload, log_time_ns)`` in recorded order."""
    k = Keys("psm")
    out: list[tuple[str, str, bytes, int]] = []

    def add(key: str, msg, t: int) -> None:  # type: ignore[no-untyped-def]
        payload, enc = encode(msg)
        out.append((key, enc, payload, t))

    obstacles = ObstacleSet(stamp_ns=1, seq=1, frame_id="base", obstacles=[
        Obstacle(id="box1", shape=Obstacle.BOX, position=vec3(0.4, 0.1, 0.2),
                 orientation=quat(0, 0, 0, 1), size=vec3(0.1, 0.1, 0.3))])
    add(k.obstacles.key, obstacles, T0_NS)
    for i in range(40):
        t = T0_NS + (i + 1) * PERIOD_NS
        sim = i * 2_000_000
        state = ArmState(stamp_ns=sim, tick=i, sim_time_ns=sim, q=[0.01 * i] * 7,
                         dq=[0.1] * 7, ee_position=vec3(0.3, 0.0, 0.4 + 0.001 * i),
                         ee_orientation=quat(0, 0, 0, 1), frame_id="base", dt_s=0.002)
        add(k.arm_state.key, state, t)
        cmd = ArmCommand(stamp_ns=sim, seq=i, tick=i, mode=ArmCommand.CARTESIAN_ACCELERATION,
                         linear_acceleration=vec3(0.0, 0.0, 0.1), source="fixture")
        add(k.arm_command.key, cmd, t + 1_000_000)
        if i % 10 == 0:
            add(k.goal("person").key,
                Goal(stamp_ns=sim, seq=i // 10, name="person", valid=True,
                     position=vec3(0.5, 0.1 * i, 0.3), covariance=[0.01, 0, 0, 0, 0.01, 0, 0, 0,
                                                                     0.01]), t + 2_000_000)
        if i % 20 == 0:
            img = CompressedImage(frame_id="cam0", format="jpeg", data=bytes(range(256)) * 4)
            img.timestamp.seconds = sim // 1_000_000_000
            img.timestamp.nanos = sim % 1_000_000_000
            add(k.camera_image("cam0").key, img, t + 3_000_000)
    return out


def write_fixture(path: Path = PATH) -> Path:
    """Write the fixture with the recorder's own writer."""
    from services.bus.recorder import McapSink

    sink = McapSink(path, overwrite=True, chunk_size=4096,
                    metadata={"project_version": "fixture", "config": "{}"})
    for key, enc, payload, t in fixture_samples():
        sink.write(key, enc, payload, t)
    sink.close()
    return path


if __name__ == "__main__":
    print(write_fixture())
