"""The planner's control path without the bus: every good arm state is answered with one
command echoing its tick; bad states and bad goals are rejected, counted, and never move the
arm; a recorded run replayed into a planner gives its commands byte for byte."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from services.bus.config import load_config
from services.bus.messages import ArmCommand, ArmState, Goal, Vec3
from services.planner.config import PlannerConfig
from services.planner.service import PlannerService

ROOT = Path(__file__).resolve().parents[2]
REPLAY = ROOT / "tests" / "data" / "planner_replay.mcap"


class _Counters:
    def add(self, _name: str, _n: int = 1) -> None:
        pass


class _FakeService:
    """What the control path uses of the bus service."""

    def __init__(self) -> None:
        self.rejections: list[str] = []
        self.log = logging.getLogger("test.planner")
        self.counters = _Counters()

    def record_rejection(self, _key: str, reason: str, _kind: str = "invalid") -> None:
        self.rejections.append(reason)


def _planner(**planner: Any) -> tuple[PlannerService, _FakeService]:
    cfg = load_config(
        PlannerConfig,
        env={},
        overrides={
            "planner.cache_dir": str(ROOT / "out" / "models"),
            **{f"planner.{k}": v for k, v in planner.items()},
        },
    )
    p = PlannerService(cfg)
    fake = _FakeService()
    p.svc = fake  # type: ignore[assignment]
    p._state_key = "psm/arm/state"
    return p, fake


def _state(tick: int, x: tuple[float, float, float] = (0.307, 0.0, 0.487), dt: float = 0.002) -> ArmState:
    st = ArmState(tick=tick, stamp_ns=tick * 2_000_000, sim_time_ns=tick * 2_000_000, dt_s=dt)
    st.ee_position.x, st.ee_position.y, st.ee_position.z = x
    st.ee_orientation.x, st.ee_orientation.w = 1.0, 0.0
    return st


def test_every_good_state_gets_one_command_echoing_its_tick() -> None:
    p, fake = _planner()
    for k in range(5):
        reply = p._answer(_state(k))
        assert reply is not None
        cmd = ArmCommand.FromString(reply)
        assert (cmd.tick, cmd.stamp_ns, cmd.seq) == (k, k * 2_000_000, k + 1)
        assert cmd.mode == ArmCommand.CARTESIAN_ACCELERATION and cmd.has_angular_velocity_reference
        q = cmd.orientation_reference
        assert abs(np.linalg.norm([q.x, q.y, q.z, q.w]) - 1.0) < 1e-9
    assert p.answered == 5 and not fake.rejections


def test_a_repeated_state_gets_the_same_command_again() -> None:
    p, _ = _planner()
    first = p._answer(_state(0))
    assert p._answer(_state(0)) == first and p.duplicate_states == 1 and p.answered == 1


@pytest.mark.parametrize(
    ("bad", "reason"),
    [
        (lambda: _state(2), "does not follow"),
        (lambda: _state(3 + 60), "tick jumped"),
        (lambda: _state(4, x=(float("nan"), 0.0, 0.4)), "non-finite"),
        (lambda: _state(4, dt=0.0), "dt_s"),
        (lambda: _with_stamp(_state(4), 4 * 2_000_000 + 5_000_000), "stamp"),
        (lambda: _with_quat(_state(4), (0.0, 0.0, 0.0, 0.0)), "quaternion norm"),
    ],
)
def test_bad_states_are_rejected_and_not_answered(bad: Any, reason: str) -> None:
    p, fake = _planner()
    for k in range(4):
        assert p._answer(_state(k)) is not None
    assert p._answer(bad()) is None
    assert p.rejected_states == 1 and reason in fake.rejections[-1], fake.rejections
    assert p._answer(_state(4)) is not None  # the planner keeps running


def _with_stamp(st: ArmState, stamp: int) -> ArmState:
    st.stamp_ns = stamp
    return st


def _with_quat(st: ArmState, q: tuple[float, float, float, float]) -> ArmState:
    o = st.ee_orientation
    o.x, o.y, o.z, o.w = q
    return st


def test_after_a_run_of_rejections_the_planner_follows_a_restarted_arm() -> None:
    p, _ = _planner(resync_after=5)
    for k in range(100, 110):
        assert p._answer(_state(k)) is not None
    answers = [p._answer(_state(k)) for k in range(5)]  # the arm restarted at tick 0
    assert answers[:4] == [None] * 4 and answers[4] is not None
    assert p.rejected_states == 4 and len(p.runner.reports) == 1


def test_bad_goals_are_rejected_and_never_used() -> None:
    p, fake = _planner()

    def goal(x: float, y: float, z: float, **kw: Any) -> Goal:
        g = Goal(
            name="person", stamp_ns=kw.pop("stamp_ns", 1), valid=True, frame_id=kw.pop("frame_id", "base")
        )
        g.position.x, g.position.y, g.position.z = x, y, z
        return g

    p._goals_prefix = "psm/goals/"
    p._on_goal(goal(float("nan"), 0.5, 0.4), "psm/goals/person")
    p._on_goal(goal(0.35, 3.0, 0.4), "psm/goals/person")
    p._on_goal(goal(0.35, 0.5, 0.4, frame_id="camera"), "psm/goals/person")
    assert p.runner.goals.rejected == 3 and "person" not in p.runner.goals.live, fake.rejections
    p._on_goal(goal(0.35, 0.5, 0.45, stamp_ns=10), "psm/goals/person")
    assert p.runner.goals.live["person"].valid
    p._on_goal(goal(0.35, 0.5, 0.45, stamp_ns=5), "psm/goals/person")  # older than the last
    assert p.runner.goals.rejected == 4 and p.runner.goals.live["person"].stamp_ns == 10


def test_a_recorded_run_replayed_into_a_planner_gives_the_same_commands() -> None:
    """tests/data/planner_replay.mcap is the start of a lockstep feeding run through the stack
    (arm states and the planner's commands, ``scripts/make_planner_replay.py``): feeding its
    states to a fresh planner in log order reproduces every recorded command: ticks, stamps and
    labels exactly, the floats to 1e-9 (on another CPU than the recording's their last bits may
    differ, as numpy picks its SIMD code paths by CPU; measured here: 6e-12 at most)."""
    from services.bus.log import read_samples

    p, fake = _planner()
    recorded: dict[int, bytes] = {}
    states: list[bytes] = []
    for sample in read_samples(REPLAY):
        if sample.topic.endswith("/arm/command"):
            recorded[ArmCommand.FromString(sample.payload).tick] = sample.payload
        elif sample.topic.endswith("/arm/state"):
            states.append(sample.payload)
    assert len(states) > 500 and len(recorded) > 500
    same: set[int] = set()
    for payload in states:
        st = ArmState.FromString(payload)
        reply = p._answer(st)
        if st.tick in recorded:
            got = _fields(ArmCommand.FromString(reply))
            want = _fields(ArmCommand.FromString(recorded[st.tick]))
            assert got[1] == want[1], f"tick {st.tick}"  # ticks, stamps, mode, frame: exact
            # accelerations [m/s²], orientation, angular velocity [rad/s]: measured 6e-12 apart
            assert got[0] == pytest.approx(want[0], rel=1e-9, abs=1e-9), f"tick {st.tick}"
            same.add(st.tick)
    assert same == set(recorded) and not fake.rejections


def _fields(msg: Any, prefix: str = "") -> tuple[dict[str, float], dict[str, Any]]:
    """A protobuf message's fields, nested ones as ``a.b``: ``(floats, everything else)``."""
    floats: dict[str, float] = {}
    other: dict[str, Any] = {}
    for fd, value in msg.ListFields():
        name = prefix + fd.name
        if fd.message_type is not None:
            f, o = _fields(value, name + ".")
            floats.update(f)
            other.update(o)
        elif fd.cpp_type in (fd.CPPTYPE_DOUBLE, fd.CPPTYPE_FLOAT):
            floats[name] = value
        else:
            other[name] = value
    return floats, other


# ---------------------------------------------------------------------------- collision predictions
class _Sample:
    def __init__(self, msg: Any, encoding: str | None = None) -> None:
        from services.bus.messages import encoding_for

        self._bytes = msg.SerializeToString()
        self.encoding = encoding or encoding_for(type(msg))
        self.payload = self

    def to_bytes(self) -> bytes:
        return self._bytes


class _Pub:
    def __init__(self) -> None:
        self.sent: list[Any] = []

    def put_bytes(self, payload: bytes) -> None:
        self.sent.append(payload)

    def put(self, msg: Any) -> None:
        self.sent.append(msg)


def _wired_planner(clock: str, **overrides: Any) -> tuple[PlannerService, _FakeService, _Pub, _Pub]:
    """A planner on ``clock`` with ``overrides``, its bus replaced by fakes: ``(planner, service,
    command publisher, goal publisher)``."""
    cfg = load_config(
        PlannerConfig,
        env={},
        overrides={"clock": clock, "planner.cache_dir": str(ROOT / "out" / "models"), **overrides},
    )
    p = PlannerService(cfg)
    fake = _FakeService()
    p.svc = fake  # type: ignore[assignment]
    p._state_key, p._pred_key = "psm/arm/state", "psm/collision"
    cmd, goal = _Pub(), _Pub()
    p._cmd_pub, p._goal_pub = cmd, goal  # type: ignore[assignment]
    return p, fake, cmd, goal


def _watched_planner(clock: str) -> tuple[PlannerService, _FakeService, _Pub, _Pub]:
    return _wired_planner(clock, **{"planner.collision_check": "required"})


def _prediction(tick: int, **fields: Any) -> Any:
    from services.bus.messages import CollisionPrediction

    m = CollisionPrediction(state_tick=tick, stamp_ns=tick * 2_000_000, **fields)
    if not m.stop_position:
        m.stop_position.extend([float("nan")] * 3)
    return m


def test_lockstep_answers_a_state_once_its_prediction_is_in() -> None:
    p, _fake, cmd, goal = _watched_planner("lockstep")
    p._on_monitor("obstacle_monitor", True)
    p._on_state(_Sample(_state(0)))
    assert cmd.sent == []  # parked: no prediction for tick 0 yet
    p._on_prediction(_Sample(_prediction(0)))
    assert [ArmCommand.FromString(b).tick for b in cmd.sent] == [0] and p.waited_states == 1
    # The planner's goal went out with the first answer (the monitor's segment end).
    assert goal.sent and goal.sent[0].name == "spoon"
    # A prediction that arrives first: the state is answered at once.
    p._on_prediction(_Sample(_prediction(1)))
    p._on_state(_Sample(_state(1)))
    assert [ArmCommand.FromString(b).tick for b in cmd.sent] == [0, 1]
    assert p.runner.state == "RUNNING"


def test_the_monitor_gone_answers_the_parked_state_with_a_brake() -> None:
    p, _fake, cmd, _goal = _watched_planner("lockstep")
    p._on_monitor("obstacle_monitor", True)
    p._on_state(_Sample(_state(0)))
    p._on_prediction(_Sample(_prediction(0)))
    p._on_state(_Sample(_state(1)))
    assert len(cmd.sent) == 1
    p._on_monitor("obstacle_monitor", False)
    assert len(cmd.sent) == 2 and p.runner.state == "HOLDING" and "not alive" in p.runner.detail
    p._on_state(_Sample(_state(2)))  # no monitor: answered at once, still braking
    assert len(cmd.sent) == 3


def test_realtime_never_waits_for_a_prediction() -> None:
    p, _fake, cmd, _goal = _watched_planner("realtime")
    p._on_monitor("obstacle_monitor", True)
    p._on_state(_Sample(_state(0)))
    assert len(cmd.sent) == 1 and p.runner.state == "HOLDING"  # no prediction yet: brake
    p._on_prediction(_Sample(_prediction(0)))
    p._on_state(_Sample(_state(1)))
    assert len(cmd.sent) == 2 and p.runner.state == "RUNNING"


@pytest.mark.parametrize(
    ("sample", "reason"),
    [
        (lambda: _Sample(_prediction(0), encoding="application/protobuf;psm.Goal"), "encoding"),
        (lambda: _Sample(Goal(name="x")), "encoding"),
        (lambda: _bad_stop(), "stop_position"),
    ],
)
def test_bad_predictions_are_rejected_and_never_used(sample: Any, reason: str) -> None:
    p, fake, _cmd, _goal = _watched_planner("realtime")
    p._on_monitor("obstacle_monitor", True)
    p._on_prediction(sample())
    assert p.rejected_predictions == 1 and reason in fake.rejections[-1]
    assert p.runner.collision is None


def _bad_stop() -> Any:
    m = _prediction(0)
    del m.stop_position[:]
    m.stop_position.extend([0.1, float("inf"), 0.0])
    return _Sample(m)


def test_a_predicted_collision_sets_the_stops_and_a_clear_path_removes_them() -> None:
    p, _fake, _cmd, _goal = _watched_planner("realtime")
    p._on_monitor("obstacle_monitor", True)
    p._on_prediction(_Sample(_prediction(0)))
    p._on_state(_Sample(_state(0)))
    hit = _prediction(1, collision=True, obstacle_id="wall")
    del hit.stop_position[:]
    hit.stop_position.extend([float("nan"), 0.31, float("nan")])
    p._on_prediction(_Sample(hit))
    p._on_state(_Sample(_state(1)))
    assert p.runner.collision_stops == 1
    kinds = [e.kind for e in p._events]
    assert "COLLISION_PREDICTED" in kinds
    p._on_prediction(_Sample(_prediction(2)))
    p._on_state(_Sample(_state(2)))
    assert "PATH_CLEAR" in [e.kind for e in p._events]


def test_random_states_never_take_the_stream_over() -> None:
    """Fuzzed states (random ticks and stamps, far more than resync_after in a row) are rejected
    and never followed: the real stream goes on, no step restarts."""
    rng = np.random.default_rng(7)
    p, _fake = _planner(resync_after=5)
    for k in range(10):
        assert p._answer(_state(k)) is not None
    for _ in range(200):
        fuzz = _state(int(rng.integers(0, 1 << 40)))
        fuzz.stamp_ns = int(rng.integers(0, 1 << 62))
        assert p._answer(fuzz) is None
    assert p._answer(_state(10)) is not None  # the real stream, unchanged
    assert p.rejected_states == 200 and len(p.runner.reports) == 1


def test_a_prediction_off_the_arms_stream_is_rejected() -> None:
    p, _fake, _cmd, _goal = _watched_planner("realtime")
    p._on_monitor("obstacle_monitor", True)
    p._on_state(_Sample(_state(0)))
    forged = _prediction(10_000)  # a tick the arm is far from
    stale = _prediction(1)
    stale.stamp_ns += 7_000_000  # a stamp that is not tick 1's
    for bad in (forged, stale):
        p._on_prediction(_Sample(bad))
    assert p.rejected_predictions == 2 and p.runner.collision is None
    p._on_prediction(_Sample(_prediction(1)))  # the real one still gets through
    assert p.runner.collision is not None and p.runner.collision.tick == 1


def test_a_goal_from_the_future_is_rejected() -> None:
    p, fake = _planner()
    p._answer(_state(0))
    p._on_goal(Goal(name="person", stamp_ns=10**18, valid=True, frame_id="base",
                    position=Vec3(x=0.4, y=0.3, z=0.4)), "psm/goals/person")
    assert "ahead of the stack's clock" in fake.rejections[-1]
    assert "person" not in p.runner.goals.live


def test_the_first_command_after_goal_updates_names_them_in_the_order_applied() -> None:
    """``ArmCommand.goal_updates``: what a recording needs to replay the planner's goal intake."""
    p, _fake, cmd, _goal = _wired_planner("realtime")
    p._goals_prefix = "psm/goals/"
    p._on_state(_Sample(_state(0)))
    p._on_goal(Goal(name="person", stamp_ns=1_000_000, valid=True, frame_id="base",
                    position=Vec3(x=0.35, y=0.5, z=0.45)), "psm/goals/person")
    p._on_goal(Goal(stamp_ns=1_500_000, valid=True, position=Vec3(x=0.35, y=3.0, z=0.45)),
               "psm/goals/person")  # outside the workspace: rejected, still applied (counted)
    p._on_goal(Goal(name="person", stamp_ns=900_000, valid=False), "psm/goals/person")  # old stamp
    p._on_state(_Sample(_state(1)))
    p._on_state(_Sample(_state(1)))  # the same state again: the same command
    p._on_state(_Sample(_state(2)))
    sent = [ArmCommand.FromString(b) for b in cmd.sent]
    assert [m.tick for m in sent] == [0, 1, 1, 2]
    named = [[(u.name, u.stamp_ns) for u in m.goal_updates] for m in sent]
    assert named == [[], [("person", 1_000_000), ("person", 1_500_000), ("person", 900_000)],
                     [("person", 1_000_000), ("person", 1_500_000), ("person", 900_000)], []]
    assert p.runner.goals.rejected == 2


def test_with_no_state_to_answer_a_command_names_only_the_latest_goal_updates() -> None:
    from services.planner.service import GOAL_UPDATES_MAX

    p, _fake, cmd, _goal = _wired_planner("realtime")
    p._goals_prefix = "psm/goals/"
    n = GOAL_UPDATES_MAX + 100
    for i in range(n):  # the arm gone for a while, the tracker still publishing
        p._on_goal(Goal(name="person", stamp_ns=i + 1, valid=True, frame_id="base",
                        position=Vec3(x=0.35, y=0.5, z=0.45)), "psm/goals/person")
    p._on_state(_Sample(_state(0)))
    stamps = [u.stamp_ns for u in ArmCommand.FromString(cmd.sent[0]).goal_updates]
    assert stamps == list(range(n - GOAL_UPDATES_MAX + 1, n + 1))


# ---------------------------------------------------------------------------- live goal sync
FRAME_NS = 1e9 / 30  # the synthetic camera's frame period at its default 30 fps


def _synced_planner(clock: str = "lockstep", **planner: Any) -> tuple[PlannerService, _FakeService, _Pub]:
    p, fake, cmd, _goal = _wired_planner(
        clock,
        **{"planner.live_goal_sync": True, "goal_tracker.synthetic.clock": "arm"},
        **{f"planner.{k}": v for k, v in planner.items()},
    )
    return p, fake, cmd


def _person(frame: int, valid: bool = True) -> Goal:
    return Goal(name="person", stamp_ns=round(frame * FRAME_NS), valid=valid, frame_id="base",
                position=Vec3(x=0.35, y=0.5, z=0.45))


def _ticks(cmd: _Pub) -> list[int]:
    return [ArmCommand.FromString(b).tick for b in cmd.sent]


def test_live_goal_sync_answers_a_state_once_the_goal_of_its_frame_is_in() -> None:
    p, _fake, cmd = _synced_planner()
    assert p._live_names == ["person"]
    p._on_state(_Sample(_state(0)))
    p._on_state(_Sample(_state(0)))  # the arm offers state 0 again: it still waits
    assert cmd.sent == []
    p._on_goal(_person(0), "psm/goals/person")
    assert _ticks(cmd) == [0] and p.waited_states == 1
    for tick in range(1, 17):  # 2 ... 32 ms: frame 0 is the one due, its goal is in
        p._on_state(_Sample(_state(tick)))
    assert _ticks(cmd) == list(range(17))
    p._on_state(_Sample(_state(17)))  # 34 ms: frame 1 (33.3 ms) is due
    assert len(cmd.sent) == 17
    p._on_goal(_person(1, valid=False), "psm/goals/person")  # no face in frame 1: still its goal
    assert _ticks(cmd)[-1] == 17 and p.waited_states == 2
    # A goal that arrives before its frame's state: the state is answered at once.
    p._on_goal(_person(2), "psm/goals/person")
    for tick in range(18, 51):
        p._on_state(_Sample(_state(tick)))
    # Up to 98 ms frame 2 (66.7 ms) is the one due; at 100 ms frame 3 is: tick 50 waits.
    assert _ticks(cmd) == list(range(50))
    p._on_goal(_person(3), "psm/goals/person")
    assert _ticks(cmd)[-1] == 50
    assert p.summary()["planner"]["live_goal_sync"]["wait_timeouts"] == 0


def test_live_goal_sync_stops_waiting_when_the_tracker_is_gone_or_a_wait_runs_out() -> None:
    p, _fake, cmd = _synced_planner(live_goal_wait_s=0.05)
    p._on_tracker("goal_tracker", True)
    p._on_state(_Sample(_state(0)))
    assert cmd.sent == []
    p._check_goal_wait()  # within the bound: still waiting
    assert cmd.sent == []
    import time

    time.sleep(0.06)
    p._check_goal_wait()
    assert _ticks(cmd) == [0] and p.goal_wait_timeouts == 1
    p._on_state(_Sample(_state(20)))  # paused until the next goal: answered at once
    assert _ticks(cmd) == [0, 20]
    p._on_goal(_person(1), "psm/goals/person")  # the sync resumes
    p._on_state(_Sample(_state(40)))  # 80 ms: frame 2 due
    assert len(cmd.sent) == 2
    p._on_tracker("goal_tracker", False)  # gone: the parked state is answered, no more waits
    assert _ticks(cmd) == [0, 20, 40]
    p._on_state(_Sample(_state(60)))
    assert _ticks(cmd)[-1] == 60


def test_live_goal_sync_has_no_effect_in_realtime_and_needs_the_arm_clock() -> None:
    p, _fake, cmd = _synced_planner("realtime")
    p._on_state(_Sample(_state(0)))
    assert _ticks(cmd) == [0] and p._frame_period is None
    from services.bus.config import ConfigError

    with pytest.raises(ConfigError, match=r"planner\.live_goal_sync: needs the synthetic camera's frames"):
        load_config(PlannerConfig, env={}, overrides={"planner.live_goal_sync": True})
