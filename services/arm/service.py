"""The ``psm arm`` service: the simulated arm on the bus.

Every tick the arm publishes :class:`~services.bus.messages.ArmState` on ``<prefix>/arm/state``
and applies the latest valid :class:`~services.bus.messages.ArmCommand` from
``<prefix>/arm/command``; link transforms go to ``<prefix>/arm/transforms`` at a lower rate. Once,
before the first state, the arm's 3-D model (its URDF meshes as a foxglove ``SceneUpdate``, one
entity per link frame of the transforms: :mod:`services.robot.arm_model`) goes to
``<prefix>/viz/arm``, latched; it is built before the bus opens.

Clock modes (the stack's ``clock``; ``docs/architecture.md``, *Time and the control loop*):

* ``realtime`` — state k is published at ``t0 + k·dt`` (wall clock) and stamped with the sim
  time ``epoch0 + k·dt`` (``epoch0`` = the UNIX time at ``t0``), so the arm's clock is locked to
  the wall clock; commands arriving before ``t0 + (k+1)·dt`` drive the step to k+1; a later
  command counts as *late*. Ticks that could not be published within one dt of their schedule
  are stepped through unpublished (``missed_ticks``, DEGRADED status) so the arm catches up.
* Sim time starts at 0 in ``lockstep`` (deterministic).
* ``lockstep`` — after publishing state k the arm waits for the command answering tick k, then
  steps at once: deterministic and as fast as the loop allows. Before the first command the arm
  re-publishes state 0 every ``lockstep_timeout_s`` (sim time does not advance without a
  planner). If a command does not come within ``lockstep_timeout_s`` the arm advances without
  it (counted in ``lockstep_timeouts``) and ticks at wall-clock pace until commands return, so
  the watchdog brakes the arm promptly when the planner stops.

Threads: a command is decoded, validated and — when it answers the state just published —
stepped on Zenoh's receive thread, under the arm's lock, as soon as it arrives. In ``realtime``
the loop thread only sleeps until each tick's schedule, steps itself when no answer came in time
(held command or brake), and publishes: one wake-up per tick on the loop thread and none for the
hand-off is what keeps a 500 Hz Python loop cheap. In ``lockstep`` the receive thread also
publishes the next state at once, so a tick costs no thread hand-off at all; the loop thread
only wakes for the timeouts (no planner yet, a planner that stopped answering) and the end.
Before and after the loop commands are queued as raw bytes and handled on the loop thread.
Either way the simulation is only ever touched by one thread at a time.
"""

from __future__ import annotations

import contextlib
import gc
import json
import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from services.arm import kernel
from services.arm.config import ArmConfig
from services.arm.sim import ArmSim
from services.arm.state_encoder import CompiledStateEncoder
from services.arm.stats import LoopStats
from services.bus.messages import ArmCommand, MessageDecodeError, decode
from services.bus.runtime import Service, ServiceApp, receive_thread_handler, run_service
from services.robot.arm_model import ArmModel, arm_model_scene
from services.robot.protocol import (
    Command,
    CommandMode,
    CommandRejectedError,
    command_from_message,
    frame_transforms,
)
from services.threads import CpuLatencyRequest, limit_blas_threads, set_realtime_priority

SERVICE_NAME = "arm"

_PUB_RING = 1 << 12  # publish times kept to match late commands to their state

#: Realtime: the service stays DEGRADED until this long passes without a missed tick, s.
DEGRADED_HOLD_S = 2.0
DEGRADED_HOLD_NS = int(DEGRADED_HOLD_S * 1e9)
#: Realtime: a longer gap (process suspended) re-anchors the schedule instead of simulating it, ns.
MAX_CATCH_UP_NS = 5_000_000_000


def command_inbox() -> queue.Queue[tuple[Any, ...]]:
    """The arm's inbox: Zenoh's threads put, the loop thread waits on it with a timeout.

    A ``queue.Queue``, never a ``queue.SimpleQueue``: in CPython 3.11 a signal that interrupts
    ``SimpleQueue.get(timeout=...)`` close to its deadline turns the wait into an unbounded one
    (the recomputed timeout goes negative, and a negative timeout means "block forever"), so a
    SIGTERM arriving while no command comes (the planner already stopped) could leave the loop
    hanging in that wait. ``Queue.get`` waits on a lock whose timeout handling after a signal
    is correct.
    """
    return queue.Queue()


class ArmService(ServiceApp):
    """The arm process: an :class:`ArmSim` driven by the bus (see module docstring).

    Built without the bus (robot model, simulator, loop state); :meth:`setup` declares the
    state and transforms publishers and the command subscriber on the skeleton's session.
    """

    name = SERVICE_NAME
    svc: Service  #: the bus service (set by :meth:`setup`)

    def __init__(self, config: ArmConfig) -> None:
        super().__init__(config)
        self.config: ArmConfig = config
        section = config.arm
        # Tiny matrices every tick: OpenBLAS's pool would busy-wait between ticks.
        limit_blas_threads(1)
        self.robot = section.load_robot()
        self.sim = ArmSim(self.robot, section)
        self.dt_ns = section.dt_ns
        self.stats = LoopStats()
        self._inbox = command_inbox()
        #: Guards the simulation between the loop thread and Zenoh's receive thread.
        self._lock = threading.Lock()
        #: Commands are handled (and stepped) on Zenoh's thread while this is set.
        self._direct = False
        self._lockstep = config.clock == "lockstep"
        #: Lockstep: ``time.monotonic()`` of the last state published (the timeouts count from it).
        self._progress_s = 0.0
        #: Lockstep: an answer has arrived (before it, state 0 is re-offered, sim time frozen).
        self._started = False
        #: Lockstep: the last timeout found no answer (the arm ticks at wall-clock pace).
        self._starved = False
        #: Lockstep: set by the receive thread when the last tick (``max_ticks``) is published.
        self._finished = threading.Event()
        self._published_tick = -1  # tick of the last published state
        # Plain lists: one element is read and written per tick (cheaper than numpy scalars).
        self._pub_ns = [0] * _PUB_RING
        self._pub_tick = [-1] * _PUB_RING
        self._answered = -1  # highest tick for which an answer has been seen
        self._payload = b""  # the encoded current state (see _encode_current)
        self._payload_tick = -1
        self._encoder = CompiledStateEncoder(
            list(self.robot.joint_names), config.arm.frame_id, self.dt_ns * 1e-9
        )
        self._tf_due_ns = -1  # sim time of the FrameTransforms to publish after the state, or -1
        v = section.validation
        self._fast_limits = (v.max_linear_acceleration, v.max_angular_velocity, v.quat_norm_tolerance)
        self._cmd_ints = np.zeros(2, dtype=np.int64)  # stamp_ns, tick of the compiled decoding
        self._tf_slot = -1
        self._degraded_since = 0  # perf_counter ns of the first miss of the current episode
        self._last_miss_ns = 0
        self._last_miss_log_ns = 0
        self._joint_names = list(self.robot.joint_names)
        self._frames = self.robot.body_frame_ids()
        rate = section.transforms_rate_hz
        # Before the bus opens, so that Zenoh's threads (which step the realtime arm when a
        # command arrives) inherit the scheduling class.
        self._rt_problem = set_realtime_priority(section.rt_priority, config.clock)
        self._cpu_latency = CpuLatencyRequest(section.cpu_latency_us)
        self._tf_every = max(1, round(1e9 / (rate * self.dt_ns))) if rate > 0 else 0
        self.model: ArmModel | None = None
        if section.model != "off":
            self.model = arm_model_scene(self.robot, 0, section.model, section.model_max_bytes)

    def zenoh_extra(self) -> dict[str, Any]:
        """The arm's state goes droppable to the clock sampler (a peer linked to the arm):
        :func:`~services.bus.messages.clock_sampler_qos`."""
        from services.bus.messages import Keys, clock_sampler_qos

        return {"qos/network": clock_sampler_qos(Keys(self.config.prefix))}

    def setup(self, svc: Service) -> None:
        """Declare the publishers, the command subscriber and the liveliness watches."""

        self.svc = svc
        self.keys = svc.keys
        if self._rt_problem:
            svc.log.warning(self._rt_problem + "; running with normal scheduling")
        if self._cpu_latency.problem:
            svc.log.warning(self._cpu_latency.problem + "; the machine's CPU idle states apply")
        elif self._cpu_latency.held:
            svc.log.info("CPU wake-up latency held", extra={"latency_us": self._cpu_latency.latency_us})
        svc.on_close(self._cpu_latency.close)
        self._state_pub = svc.publisher(self.keys.arm_state)
        self._tf_pub = svc.publisher(self.keys.arm_transforms) if self._tf_every else None
        self._model_pub = svc.publisher(self.keys.arm_model) if self.model is not None else None
        if self.model is not None:
            svc.log.info(
                "arm model",
                extra={"kind": self.config.arm.model, "bytes": self.model.message.ByteSize(),
                       "triangles": self.model.triangles_out, "of": self.model.triangles_in,
                       "cell_mm": round(self.model.cell_m * 1e3, 3), "skipped": ",".join(self.model.skipped)},
            )
        self._cmd_key = self.keys.arm_command.key
        self._cmd_encoding = self.keys.arm_command.encoding
        # On Zenoh's receive thread (no hop through a Python callback thread): see _on_sample.
        self._cmd_sub = svc.session.declare_subscriber(
            self._cmd_key, receive_thread_handler(self._on_sample)
        )
        svc.on_close(self._undeclare)
        if self.config.arm.watch_services:
            svc.watch_liveliness(self.config.arm.watch_services, self._on_liveliness)

    # ------------------------------------------------------------------ zenoh threads
    def _on_sample(self, sample: Any) -> None:
        # Zenoh's receive thread. Realtime: handle the command here and, if it answers the
        # state just published, compute the next state at once; otherwise only enqueue.
        item = (time.perf_counter_ns(), sample.payload.to_bytes(), str(sample.encoding))
        if not self._direct:
            self._inbox.put(item)
            return
        with self._lock:
            if not self._direct:  # the loop stopped while this thread waited for the lock
                self._inbox.put(item)
                return
            tick = self._handle(item)
            sim = self.sim
            if self._lockstep:
                if tick >= sim.tick == self._published_tick:
                    self._started = True
                    self._starved = False
                    self._lockstep_step()
            elif tick == sim.tick == self._published_tick and self._may_step():
                self._advance(1)

    def _on_liveliness(self, name: str, alive: bool) -> None:
        if alive:
            return
        item = (time.perf_counter_ns(), None, name)
        if not self._direct:
            self._inbox.put(item)
            return
        with self._lock:
            self._handle(item)

    def _undeclare(self) -> None:
        with contextlib.suppress(Exception):
            self._cmd_sub.undeclare()

    # ------------------------------------------------------------------ loop helpers
    def _handle(self, item: tuple[Any, ...]) -> int:
        """Process one inbox item; returns the tick it answers (-1 if unknown)."""
        t_recv, payload, encoding = item
        sim = self.sim
        if payload is None:
            self.svc.log.warning("watched service lost: braking", extra={"service": encoding})
            sim.drop_command()
            return -1
        self.svc.counters.add("received")
        # A plain, valid Cartesian command is decoded and checked in one compiled call; anything
        # else (or what that call does not decide) goes through protobuf and validate_command.
        flags = kernel.COMMAND_SLOW
        if encoding == self._cmd_encoding:
            vals = np.empty(10)
            flags = kernel.parse_cartesian_command(
                np.frombuffer(payload, dtype=np.uint8), *self._fast_limits, vals, self._cmd_ints
            )
        if flags >= 0:
            stamp, tick = self._cmd_ints.tolist()
            cmd = Command(
                tick, CommandMode.CARTESIAN, vals[0:3],
                vals[3:7] if flags & kernel.COMMAND_HAS_ORIENTATION else None,
                vals[7:10] if flags & kernel.COMMAND_HAS_ANGULAR_VELOCITY else None,
            )
        else:
            try:
                msg = decode(payload, encoding, ArmCommand)
                cmd = command_from_message(msg)  # type: ignore[arg-type]
            except MessageDecodeError as exc:
                sim.reject("malformed", str(exc))
                self.svc.record_rejection(self._cmd_key, str(exc), exc.kind)
                return -1
            except CommandRejectedError as exc:
                sim.reject(exc.reason, str(exc))
                self.svc.record_rejection(self._cmd_key, str(exc), exc.reason)
                return int(msg.tick)  # type: ignore[attr-defined]
            tick = cmd.tick
            stamp = int(msg.stamp_ns)  # type: ignore[attr-defined]
        if tick <= sim.tick and stamp != sim.time_origin_ns + tick * self.dt_ns:
            # A command echoes the stamp of the state it answers: this one answers no state the
            # arm published (a forged, replayed or corrupted command).
            why = f"command for tick {tick} has stamp {stamp}, not the stamp of that state"
            sim.reject("stamp", why)
            self.svc.record_rejection(self._cmd_key, why, "stamp")
            return -1
        before = sim.counters["rejected"]
        if flags >= 0:
            sim.submit_validated(cmd)
        else:
            sim.submit(cmd)
        if sim.counters["rejected"] > before:
            self.svc.record_rejection(self._cmd_key, sim.last_rejection, sim.last_rejection_reason)
        if tick > self._answered:
            slot = tick % _PUB_RING
            if self._pub_tick[slot] == tick:
                lat = t_recv - self._pub_ns[slot]
                self.stats.add_latency(lat)
                self.stats.answered_ticks += 1
                if lat > self.dt_ns and self.config.clock == "realtime":
                    self.stats.late_commands += 1
            self._answered = tick
        return tick

    def _encode_current(self) -> None:
        """Serialise the current state for :meth:`_put_current` (and, on a transforms tick, mark
        its FrameTransforms due, stamped with the same sim time)."""
        sim = self.sim
        snap = sim.snapshot()
        self._payload = self._encoder.encode(
            snap, watchdog_tripped=sim.watchdog_tripped, rejected_commands=sim.counters["rejected"]
        )
        self._payload_tick = snap.tick
        self._tf_due_ns = -1
        if self._tf_pub is not None:
            slot = snap.tick // self._tf_every
            if slot != self._tf_slot:  # first tick of a transforms period (also after a skip)
                self._tf_slot = slot
                self._tf_due_ns = snap.time_ns

    def _put_current(self) -> int:
        """Publish what :meth:`_encode_current` prepared; returns the ``perf_counter_ns`` time of
        the state's ``put``. Due FrameTransforms are built after that ``put`` (the simulation
        still holds the published state), off the state's path."""
        now = time.perf_counter_ns()
        self._state_pub.put_bytes(self._payload)
        tick = self._payload_tick
        slot = tick % _PUB_RING
        self._pub_ns[slot] = now
        self._pub_tick[slot] = tick
        self.stats.published_ticks += 1
        if self._tf_due_ns >= 0 and self._tf_pub is not None:
            self.sim.sync_model()
            self._tf_pub.put(
                frame_transforms(self.robot, self._frames, self._tf_due_ns, self.config.arm.frame_id)
            )
            self._tf_due_ns = -1
        return now

    def _publish_state(self) -> int:
        """Lockstep: publish the current state, then prepare the next step while the command is
        in flight; returns the ``perf_counter_ns`` time of the state's ``put``."""
        self._encode_current()
        now = self._put_current()
        self._published_tick = self.sim.tick
        self._progress_s = time.monotonic()
        self.sim.prepare()
        if not self._may_step():
            self._finished.set()
        return now

    def _lockstep_step(self) -> None:
        """Lockstep, under the lock: step once with the held command (or brake) and publish the
        new state, unless ``max_ticks`` is reached."""
        if self._may_step():
            self.sim.step()
            self.stats.ticks += 1
            self._publish_state()

    def _may_step(self) -> bool:
        """False once ``max_ticks`` is reached (the loop then publishes that state and stops)."""
        max_ticks = self.config.arm.max_ticks
        return max_ticks <= 0 or self.sim.tick < max_ticks

    def _advance(self, n: int) -> None:
        """Step ``n`` ticks with the held command (or brake), then encode the new state and do
        the command-independent work of the step after it. Realtime: called under the lock."""
        sim = self.sim
        for _ in range(n):
            sim.step()
        self.stats.ticks += n
        self._encode_current()
        sim.prepare()

    def _drain(self) -> None:
        while True:
            try:
                item = self._inbox.get_nowait()
            except queue.Empty:
                return
            self._handle(item)

    def _wait_for_subscribers(self, timeout_s: float) -> None:
        """Lockstep: give Zenoh time to route the state to existing subscribers before tick 0
        (the publisher's matching status)."""
        deadline = time.monotonic() + timeout_s
        while (
            self._state_pub.has_subscribers is False
            and time.monotonic() < deadline
            and not self.svc.stop_event.is_set()
        ):
            time.sleep(0.005)

    def _done(self) -> bool:
        max_ticks = self.config.arm.max_ticks
        return self.svc.stop_event.is_set() or (0 < max_ticks <= self.sim.tick)

    def _publish_model(self) -> None:
        """Publish the arm model (latched) stamped with the arm's clock at its start: the sim
        time of the current tick in lockstep, the wall clock in realtime (the loop sets the sim
        time's origin to it at once)."""
        if self.model is None or self._model_pub is None:
            return
        stamp = self.sim.time_ns if self._lockstep else time.time_ns()
        sec, nsec = divmod(stamp, 1_000_000_000)
        for e in self.model.message.entities:
            e.timestamp.seconds, e.timestamp.nanos = sec, nsec
        self._model_pub.put(self.model.message)

    # ------------------------------------------------------------------ loops
    def run_realtime(self) -> None:
        """Realtime loop: state k is published at ``t0 + k·dt`` by the wall clock, stamped
        ``epoch0 + k·dt`` (``epoch0`` = UNIX time at ``t0``).

        The step k → k+1 is computed as soon as the command answering k arrives, on Zenoh's
        receive thread (:meth:`_on_sample`), together with state k+1's encoding and the
        command-independent work for the step after it; this thread steps at the deadline
        ``t0 + (k+1)·dt`` instead when no answer came (held command or braking), and publishes
        state k+1 at its scheduled time, so the publication jitter does not include the
        computation. A tick whose schedule has passed by a whole period before it could be
        published (the process was not running in time) is *missed*: the simulation steps
        through the missed ticks without publishing them (held command, watchdog, limits as
        usual) and publishes the current tick, so sim time stays locked to the wall clock.
        Missed ticks are counted, logged (rate-limited) and set the service DEGRADED until
        :data:`DEGRADED_HOLD_S` passes without one.
        """
        sim, stats, period = self.sim, self.stats, self.dt_ns
        clock = time.perf_counter_ns
        sleep = time.sleep
        with self._lock:
            t0 = clock()
            sim.set_time_origin(time.time_ns())
            anchor_tick = k = sim.tick  # k: the next tick to publish
            self._drain()
            self._encode_current()
            sim.prepare()
            self._direct = True
        try:
            while True:
                sched = t0 + (k - anchor_tick) * period
                behind = (clock() - sched) // period
                if behind > 0:
                    while behind > 0:  # catching up takes time too: until the current tick is due
                        t0, anchor_tick, k = self._catch_up(behind, t0, anchor_tick, k)
                        sched = t0 + (k - anchor_tick) * period
                        behind = (clock() - sched) // period
                elif self._degraded_since and clock() - self._last_miss_ns > DEGRADED_HOLD_NS:
                    self._degraded_since = 0
                    self.svc.set_degraded(None)
                    self.svc.log.info("realtime recovered: no missed tick for %.1f s", DEGRADED_HOLD_S)
                remaining = sched - clock()
                if remaining > 0:
                    sleep(remaining * 1e-9)
                woke = clock()
                with self._lock:
                    locked = clock()
                    if sim.tick < k:  # no answer to the last state in time
                        self._advance(k - sim.tick)
                    put = self._put_current()
                    self._published_tick = sim.tick
                late = put - sched
                stats.add_jitter(late)
                if late > period:
                    stats.add_miss(k, woke - sched, locked - woke, put - locked)
                if self._done():
                    break
                k += 1
        finally:
            with self._lock:
                self._direct = False

    def _catch_up(self, behind: int, t0: int, anchor_tick: int, k: int) -> tuple[int, int, int]:
        """Tick ``k``'s schedule passed ``behind`` whole periods ago: step through those ticks
        without publishing them and return the (possibly re-anchored) schedule
        ``(t0, anchor_tick, k)`` with the tick to publish next. A gap longer than
        :data:`MAX_CATCH_UP_NS` is not simulated: the schedule is re-anchored at tick ``k``
        (sim time then lags the wall clock by the gap; counted in ``reanchors``)."""
        stats, period = self.stats, self.dt_ns
        now = time.perf_counter_ns()
        stats.missed_ticks += behind
        stats.skipped_ticks += behind
        self._last_miss_ns = now
        if behind * period > MAX_CATCH_UP_NS:
            stats.reanchors += 1
            t0, anchor_tick = now, k
        else:
            k += behind
            with self._lock:
                self._advance(k - self.sim.tick)
        reason = (
            f"realtime: {stats.skipped_ticks} ticks missed "
            f"(last gap {behind} ticks, {behind * period * 1e-6:.1f} ms)"
        )
        if not self._degraded_since:
            self._degraded_since = now
        self.svc.set_degraded(reason)
        if now - self._last_miss_log_ns >= 1_000_000_000:
            self._last_miss_log_ns = now
            self.svc.log.warning(
                "missed ticks: stepped through them, publishing the current tick",
                extra={"gap_ticks": behind, "missed_total": stats.missed_ticks,
                       "skipped_total": stats.skipped_ticks, "reanchors": stats.reanchors},
            )
        return t0, anchor_tick, k

    def run_lockstep(self) -> None:
        """Lockstep loop: tick k+1 follows as soon as the command answering tick k arrived.

        The step, the publication of state k+1 and the command-independent work for the step
        after it run on Zenoh's receive thread when the answer arrives (:meth:`_on_sample`).
        This thread only waits: for ``lockstep_timeout_s`` without a published state (before
        the first answer it re-offers state 0; afterwards it counts a lockstep timeout and steps
        without an answer, then every ``dt`` until answers return), for ``max_ticks`` and for
        the stop.
        """
        timeout_s = self.config.arm.lockstep_timeout_s
        dt_s = self.dt_ns * 1e-9
        clock = time.monotonic
        self._wait_for_subscribers(timeout_s)
        with self._lock:
            self._drain()
            # Direct before the first state goes out: its answer may arrive at once.
            self._direct = True
            self._publish_state()
        try:
            while not self._done() and not self._finished.is_set():
                wait_s = (dt_s if self._starved else timeout_s) - (clock() - self._progress_s)
                if wait_s > 0:
                    # Short slices: the stop (a signal) is seen at once.
                    self._finished.wait(min(wait_s, 0.1))
                    continue
                with self._lock:
                    if clock() - self._progress_s < (dt_s if self._starved else timeout_s):
                        continue  # a state was published while this thread took the lock
                    if not self._started:  # no planner yet: re-offer state 0, sim time frozen
                        self._publish_state()
                        continue
                    self.stats.lockstep_timeouts += 1
                    self._starved = True
                    self._lockstep_step()
        finally:
            with self._lock:
                self._direct = False

    def run(self) -> dict[str, Any]:
        """Run on the bus until stopped (signal, ``max_ticks``); returns the stats summary."""
        run_service(self, install_signals=threading.current_thread() is threading.main_thread())
        return self.summary()

    def loop(self, svc: Service) -> None:
        """The control loop of the configured clock."""
        section = self.config.arm
        svc.log.info(
            "arm running",
            extra={
                "clock": self.config.clock,
                "dt_s": section.dt_s,
                "ee_frame": self.robot.ee_frame,
                "urdf": self.robot.urdf_path,
                "joints": self.robot.n,
            },
        )
        self._publish_model()
        gc.collect()
        gc.freeze()
        t0 = time.perf_counter()
        try:
            if self.config.clock == "lockstep":
                self.run_lockstep()
            else:
                self.run_realtime()
        finally:
            self.stats.wall_s = time.perf_counter() - t0

    def teardown(self, svc: Service) -> None:
        """Log the counters and write the statistics file."""
        svc.log.info("arm stopped", extra={"ticks": self.stats.ticks, **dict(self.sim.counters.items())})
        if self.config.arm.stats_file:
            Path(self.config.arm.stats_file).write_text(json.dumps(self.summary(), indent=2))

    def summary(self) -> dict[str, Any]:
        """Loop statistics + simulation counters + service counters."""
        out = self.stats.summary()
        out["clock"] = self.config.clock
        out["dt_s"] = self.config.arm.dt_s
        out["sim_counters"] = dict(self.sim.counters)
        svc = getattr(self, "svc", None)
        out["service_counters"] = svc.counters.snapshot() if svc is not None else {}
        out["final_tick"] = self.sim.tick
        return out


def main(config: ArmConfig) -> int:
    """Run the arm service with a loaded config; returns the exit code."""
    return run_service(ArmService(config))
