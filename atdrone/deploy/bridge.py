"""The bridge to the drones: one protocol for the loop, implemented with cflib.

:class:`CflibBridge` drives Crazyflies through cflib (Bitcraze's library, GPLv3, the
``atdrone[deploy]`` extra, imported only when a bridge opens): ``Swarm`` with a
``CachedCfFactory`` whose TOC cache persists between runs; ``open`` gives up after
``connect_timeout`` s. Per drone the Kalman estimator (``stabilizer.estimator`` = 2),
the Mellinger controller (``stabilizer.controller`` = 2), the trust in motion capture
(``locSrv.extPosStdDev``, ``locSrv.extQuatStdDev``) and the high-level commander are
set and confirmed; two log blocks stream the battery, the onboard state estimate
(position and yaw), the supervisor's state bits and the estimator's position variances.

What the firmware needs, and how the bridge gives it (facts: docs/deploy.md):

- **Estimator yaw**: poses go out as ``send_extpose`` (position and the mocap
  quaternion), and :meth:`reset_estimators` sets ``kalman.initialYaw`` to the drones'
  physical yaw, toggles ``kalman.resetEstimation`` and waits until ``kalman.varPX/PY/PZ``
  settle (as cflib's ``Swarm.reset_estimators`` does).
- **Setpoints**: full-state setpoints (position, velocity, acceleration) along the
  loop's reference, at one constant physical yaw (:attr:`yaw`).
- **Hand-over**: per drone the high-level command goes first, then
  ``notify_setpoint_stop`` (an idle planner would send motors-off); takeoff, land and
  go_to carry the physical yaw (cflib's default 0 would turn the drones to +x).
- **No blocking in the loop**: one sender thread owns the radio: a FIFO of commands,
  a latest-value mailbox of setpoints (sent as soon as posted) and one of poses (sent
  at ``pose_rate`` Hz, 30-50 Hz is what a radio carries for a few drones). The loop and
  the motion-capture thread only post.
- **Dead-man heartbeat**: :meth:`start_heartbeat` starts a thread that sends the
  supervisor's emergency-stop watchdog packet every ``heartbeat_period`` s to every
  drone, but only while the loop's last :meth:`beat` is younger than
  ``heartbeat_timeout`` s. Once the first packet arrived the firmware stops the motors
  1 s after the last one: a hung loop, a blocked radio or a dead process stops every
  drone within ``heartbeat_timeout + 1`` s. An ``urgent()`` request (a second Ctrl-C)
  sends the emergency stop from this thread at once.

Radio URIs fly real drones; ``simradio://``/``udp://`` URIs fly the simulated fleet
(:mod:`atdrone.deploy.simfleet`) through exactly the same code.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from atdrone.deploy.clock import Clock, RealClock
from atdrone.errors import UserError
from atdrone.fileio import user_cache

MELLINGER, KALMAN = 2, 2
BIT_CAN_FLY, BIT_LOCKED = 3, 6
VARIANCE_SETTLED = 0.001  # m^2: the spread of the last 10 variances cflib's reset_estimators waits for
ARM_TIMEOUT = 10.0  # s: how long armed drones, on the floor, get to report that they can fly

Setpoint = tuple[np.ndarray, np.ndarray, np.ndarray]  # position, velocity, acceleration (3,) each


class BridgeError(UserError, RuntimeError):
    """A drone cannot be reached or set up."""


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a level attitude at ``yaw`` radians."""
    return 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)


class Bridge(Protocol):
    """What the deploy loop needs from the drones (names in config order)."""

    names: tuple[str, ...]
    yaw: float

    def open(self) -> None: ...

    def close(self) -> None: ...

    def reset_estimators(self, timeout: float = 10.0) -> None: ...

    def battery(self) -> dict[str, float]: ...

    def estimates(self) -> dict[str, tuple[float, float, float, float]]: ...

    def supervisor(self) -> dict[str, int]: ...

    def link_age(self) -> dict[str, float]: ...

    def arm(self, names: Sequence[str], timeout: float = ARM_TIMEOUT) -> None: ...

    def request_arming(self, names: Sequence[str]) -> None: ...

    def takeoff(self, names: Sequence[str], height: float, duration: float) -> None: ...

    def go_to(self, name: str, pos: np.ndarray, duration: float) -> None: ...

    def land(self, names: Sequence[str], duration: float) -> None: ...

    def notify_stop(self, names: Sequence[str]) -> None: ...

    def post_setpoints(self, setpoints: Mapping[str, Setpoint]) -> None: ...

    def post_poses(self, poses: Mapping[str, tuple[np.ndarray, np.ndarray | None]]) -> None: ...

    def emergency_stop(self, names: Sequence[str]) -> None: ...

    def beat(self) -> None: ...

    def start_heartbeat(self, urgent: Callable[[], bool]) -> None: ...

    def stop_heartbeat(self) -> None: ...

    def sender_age(self) -> float: ...

    def sent(self) -> Counter[str]: ...


class CflibBridge:
    """The bridge over cflib (see the module docstring)."""

    def __init__(
        self,
        uris: Mapping[str, str],
        clock: Clock | None = None,
        yaw: float = math.pi / 2,
        extpos_std: float = 0.01,
        extquat_std: float = 0.01,
        connect_timeout: float = 10.0,
        cache_dir: str | Path | None = None,
        pose_rate: float = 50.0,
        heartbeat_period: float = 0.1,
        heartbeat_timeout: float = 0.3,
    ) -> None:
        self.names = tuple(uris)
        self.uris = dict(uris)
        self.clock: Clock = clock or RealClock()
        self.yaw = float(yaw)
        self.extpos_std, self.extquat_std = extpos_std, extquat_std
        self.connect_timeout = connect_timeout
        self.cache_dir = Path(cache_dir) if cache_dir else user_cache("cflib-toc")
        self.pose_rate = pose_rate
        self.heartbeat_period, self.heartbeat_timeout = heartbeat_period, heartbeat_timeout
        self._cf: dict[str, Any] = {}
        self._swarm: Any = None
        self._vbat = dict.fromkeys(self.names, math.nan)
        self._estimate = dict.fromkeys(self.names, (math.nan, math.nan, math.nan, math.nan))
        self._bits = dict.fromkeys(self.names, 0)
        self._variance: dict[str, deque[tuple[float, float, float]]] = {n: deque(maxlen=10) for n in self.names}
        self._heard = dict.fromkeys(self.names, -math.inf)
        self._sent: Counter[str] = Counter()
        self._lock = threading.Lock()
        # the sender: commands in order, the latest setpoint and pose per drone
        self._commands: deque[tuple[str, Callable[[], None]]] = deque()
        self._setpoints: dict[str, Setpoint] = {}
        self._poses: dict[str, tuple[np.ndarray, np.ndarray | None]] = {}
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._sender: threading.Thread | None = None
        self._sender_t = math.inf  # clock time the sender last finished a round
        # the heartbeat
        self._beat = -math.inf
        self._heartbeat: threading.Thread | None = None
        self._heartbeat_stop = threading.Event()
        self.heartbeats = 0
        self.urgent_stop = False

    # ------------------------------------------------------------ link
    def open(self) -> None:
        """Connect every drone (within ``connect_timeout``), set its parameters, start its logs and the sender."""
        import cflib.crtp
        from cflib.crazyflie.swarm import CachedCfFactory, Swarm

        cflib.crtp.init_drivers()
        if any(u.startswith("simradio://") for u in self.uris.values()):
            from atdrone.deploy.simfleet import register_simradio

            register_simradio()
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        swarm = Swarm(list(self.uris.values()), factory=CachedCfFactory(rw_cache=str(self.cache_dir)))
        errors: list[BaseException] = []

        def connect() -> None:
            try:
                swarm.open_links()
            except BaseException as exc:  # cflib raises bare Exceptions
                errors.append(exc)

        thread = threading.Thread(target=connect, name="cflib-open", daemon=True)
        thread.start()
        thread.join(self.connect_timeout)
        by_uri = {u: n for n, u in self.uris.items()}
        if thread.is_alive() or errors:
            silent = [by_uri[u] for u, scf in swarm._cfs.items() if not scf.is_link_open()]
            why = "no answer" if thread.is_alive() else f"{type(errors[0]).__name__}: {errors[0]}"
            for scf in swarm._cfs.values():  # what did open is closed again
                if scf.is_link_open():
                    scf.close_link()
                else:
                    scf.cf.close_link()
            raise BridgeError(
                f"cannot connect {', '.join(silent) or 'the drones'} within {self.connect_timeout:g} s ({why})"
            )
        self._swarm = swarm
        self._cf = {by_uri[u]: scf.cf for u, scf in swarm._cfs.items()}
        for name, cf in self._cf.items():
            self._setup(name, cf)
        self._sender = threading.Thread(target=self._send_loop, name="bridge-sender", daemon=True)
        self._sender.start()

    def _setup(self, name: str, cf: Any) -> None:
        from cflib.crazyflie.log import LogConfig

        # cflib's link statistics ping every link from a thread of its own and take percentiles of the latencies
        # on every answer: work in the ground station's interpreter that the flight does not use (link health
        # comes from the packets received, below)
        with contextlib.suppress(Exception):
            cf.link_statistics.stop()

        cf.packet_received.add_callback(lambda _pk, n=name: self._heard.__setitem__(n, time.monotonic()))
        self._heard[name] = time.monotonic()
        settings = (
            ("stabilizer.estimator", KALMAN),
            ("stabilizer.controller", MELLINGER),
            ("locSrv.extPosStdDev", self.extpos_std),
            ("locSrv.extQuatStdDev", self.extquat_std),
            ("commander.enHighLevel", 1),
        )
        for param, value in settings:
            cf.param.set_value(param, value)
            self._sent["param"] += 1
        for param, value in settings:
            self._confirm(name, cf, param, value)
        state = LogConfig(name="state", period_in_ms=100)
        for var in ("pm.vbat", "stateEstimate.x", "stateEstimate.y", "stateEstimate.z", "stateEstimate.yaw"):
            state.add_variable(var, "float")
        state.add_variable("supervisor.info", "uint16_t")
        cf.log.add_config(state)
        state.data_received_cb.add_callback(lambda _ts, data, _cfg, n=name: self._on_state(n, data))
        state.start()
        variance = LogConfig(name="variance", period_in_ms=100)
        for var in ("kalman.varPX", "kalman.varPY", "kalman.varPZ"):
            variance.add_variable(var, "float")
        cf.log.add_config(variance)
        variance.data_received_cb.add_callback(
            lambda _ts, data, _cfg, n=name: self._variance[n].append(
                (data["kalman.varPX"], data["kalman.varPY"], data["kalman.varPZ"])
            )
        )
        variance.start()

    def _on_state(self, name: str, data: Mapping[str, float]) -> None:
        self._vbat[name] = data["pm.vbat"]
        self._estimate[name] = (
            data["stateEstimate.x"],
            data["stateEstimate.y"],
            data["stateEstimate.z"],
            math.radians(data["stateEstimate.yaw"]),
        )
        self._bits[name] = int(data["supervisor.info"])

    @staticmethod
    def _confirm(name: str, cf: Any, param: str, value: float, timeout: float = 3.0) -> None:
        """Wait until the drone has acknowledged ``param`` = ``value`` (its write answer updates cflib's copy)."""
        group, key = param.split(".")
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            seen = cf.param.values.get(group, {}).get(key)
            if seen is not None and math.isclose(float(seen), float(value), rel_tol=1e-6):
                return
            time.sleep(0.01)
        raise BridgeError(f"{name}: {param} not confirmed as {value} within {timeout:g} s")

    def reset_estimators(self, timeout: float = 10.0) -> None:
        """Set every estimator's initial yaw to :attr:`yaw`, reset it, wait until its position variance settles.

        Poses must already flow (:meth:`post_poses`), or the variances never settle and
        this raises :class:`BridgeError` after ``timeout`` wall seconds.
        """
        for name, cf in self._cf.items():
            cf.param.set_value("kalman.initialYaw", self.yaw)
            self._confirm(name, cf, "kalman.initialYaw", self.yaw)
            self._variance[name].clear()
            cf.param.set_value("kalman.resetEstimation", 1)
        time.sleep(0.1)
        for cf in self._cf.values():
            cf.param.set_value("kalman.resetEstimation", 0)
        self._count("estimator_reset", len(self._cf))
        end = time.monotonic() + timeout
        pending = set(self._cf)
        while pending and time.monotonic() < end:
            for name in list(pending):
                history = list(self._variance[name])
                if len(history) == 10 and all(
                    max(v[k] for v in history) - min(v[k] for v in history) < VARIANCE_SETTLED for k in range(3)
                ):
                    pending.discard(name)
            time.sleep(0.02)
        if pending:
            raise BridgeError(f"estimator of {', '.join(sorted(pending))} did not settle within {timeout:g} s")

    def close(self) -> None:
        """Stop the heartbeat and the sender, close every link (cflib sends a zero-thrust setpoint as it closes)."""
        self.stop_heartbeat()
        self._closing.set()
        self._wake.set()
        if self._sender is not None:
            self._sender.join(timeout=3)
            self._sender = None
        if self._swarm is not None:
            links = list(self._swarm._cfs.values())

            def close_link(scf: Any) -> None:
                # cflib's ping thread first: a ping on a closing socket reports a link error on that thread,
                # whose disconnect callback joins the thread itself (it dies with a RuntimeError)
                with contextlib.suppress(Exception):
                    scf.cf.link_statistics.stop()
                with contextlib.suppress(Exception):  # a link that is already gone
                    scf.close_link()

            # together: cflib waits up to 1 s for each link's receiving thread to end
            with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, len(links))) as pool:
                list(pool.map(close_link, links))
            self._swarm = None

    # ------------------------------------------------------------ state
    def battery(self) -> dict[str, float]:
        return dict(self._vbat)

    def estimates(self) -> dict[str, tuple[float, float, float, float]]:
        """The onboard state estimate of every drone: x, y, z (m) and yaw (radians)."""
        return dict(self._estimate)

    def supervisor(self) -> dict[str, int]:
        """The supervisor's state bits of every drone, as last logged."""
        return dict(self._bits)

    def link_age(self) -> dict[str, float]:
        now = time.monotonic()
        return {n: now - t for n, t in self._heard.items()}

    def sender_age(self) -> float:
        """Clock seconds since the sender last finished a round (large: the radio blocks)."""
        return self.clock.now() - self._sender_t if math.isfinite(self._sender_t) else 0.0

    def sent(self) -> Counter[str]:
        with self._lock:
            return Counter(self._sent)

    def _count(self, kind: str, n: int = 1) -> None:
        with self._lock:
            self._sent[kind] += n

    # ------------------------------------------------------------ commands (blocking, before the flight)
    def arm(self, names: Sequence[str], timeout: float = ARM_TIMEOUT) -> None:
        """Request arming, then wait until each supervisor reports it can fly (or raise BridgeError).

        Each read of the can-fly bit is a request and its answer (cflib waits 0.2 s for it, one drone at a
        time); on a starved host answers come late, so the drones, still on the floor and disarmed until they
        answer, get :data:`ARM_TIMEOUT` seconds in all."""
        for n in names:
            self._cf[n].supervisor.send_arming_request(True)
        self._count("arming", len(names))
        end = time.monotonic() + timeout
        pending = set(names)
        while pending and time.monotonic() < end:
            pending = {n for n in pending if not self._cf[n].supervisor.can_fly}
        if pending:
            raise BridgeError(
                f"{', '.join(sorted(pending))} cannot fly {timeout:g} s after arming (supervisor's can-fly bit)"
            )

    # ------------------------------------------------------------ commands (queued for the sender)
    def _queue(self, name: str, kind: str, fn: Callable[[], None]) -> None:
        with self._lock:
            self._setpoints.pop(name, None)  # a setpoint posted before must not override the command
            self._commands.append((kind, fn))
        self._wake.set()

    def request_arming(self, names: Sequence[str]) -> None:
        """Queue an arming request (in order, before a takeoff queued after it; an armed drone ignores it)."""
        for n in names:
            self._queue(n, "arming", partial(self._cf[n].supervisor.send_arming_request, True))

    def takeoff(self, names: Sequence[str], height: float, duration: float) -> None:
        for n in names:
            hl = self._cf[n].high_level_commander
            self._queue(n, "takeoff", partial(hl.takeoff, height, duration, yaw=self.yaw))

    def go_to(self, name: str, pos: np.ndarray, duration: float) -> None:
        x, y, z = (float(v) for v in pos)
        self._queue(name, "go_to", partial(self._cf[name].high_level_commander.go_to, x, y, z, self.yaw, duration))

    def land(self, names: Sequence[str], duration: float) -> None:
        for n in names:
            self._queue(n, "land", partial(self._cf[n].high_level_commander.land, 0.0, duration, yaw=self.yaw))

    def notify_stop(self, names: Sequence[str]) -> None:
        """Hand the drones to the high-level commander: queue this AFTER their high-level command."""
        for n in names:
            self._queue(n, "notify_stop", self._cf[n].commander.send_notify_setpoint_stop)

    def post_setpoints(self, setpoints: Mapping[str, Setpoint]) -> None:
        """The latest full-state setpoint per drone; sent by the sender as soon as it can (never blocks)."""
        with self._lock:
            self._setpoints.update(setpoints)
        self._wake.set()

    def post_poses(self, poses: Mapping[str, tuple[np.ndarray, np.ndarray | None]]) -> None:
        """The latest motion-capture pose per drone: position (3,), quaternion (w, x, y, z) or None."""
        with self._lock:
            self._poses.update(poses)

    def emergency_stop(self, names: Sequence[str]) -> None:
        """Motors off now, sent from the calling thread (not queued behind anything)."""
        for n in names:
            with contextlib.suppress(Exception):
                self._cf[n].supervisor.send_emergency_stop()
        self._count("estop", len(names))

    # ------------------------------------------------------------ the sender thread
    def _send_loop(self) -> None:
        period = 1.0 / self.pose_rate
        next_pose = self.clock.now()
        while not self._closing.is_set():
            self._wake.wait(max(0.0, (next_pose - self.clock.now()) / self.clock.rate))
            self._wake.clear()
            with self._lock:
                commands, self._commands = list(self._commands), deque()
                setpoints, self._setpoints = self._setpoints, {}
            for kind, fn in commands:
                with contextlib.suppress(Exception):  # a link closing under us
                    fn()
                self._count(kind)
            for n, (pos, vel, acc) in setpoints.items():
                with contextlib.suppress(Exception):
                    self._cf[n].commander.send_full_state_setpoint(
                        [float(v) for v in pos],
                        [float(v) for v in vel],
                        [float(v) for v in acc],
                        yaw_quaternion(self.yaw),
                        0.0,
                        0.0,
                        0.0,
                    )
                self._count("setpoint")
            if self.clock.now() >= next_pose:
                next_pose = self.clock.now() + period
                with self._lock:
                    poses, self._poses = self._poses, {}
                for n, (p, q) in poses.items():
                    cf = self._cf.get(n)
                    if cf is None:
                        continue
                    with contextlib.suppress(Exception):
                        if q is None:
                            cf.extpos.send_extpos(float(p[0]), float(p[1]), float(p[2]))
                        else:  # cflib takes x, y, z, w
                            cf.extpos.send_extpose(
                                *(float(v) for v in p), float(q[1]), float(q[2]), float(q[3]), float(q[0])
                            )
                    self._count("extpose" if q is not None else "extpos")
            self._sender_t = self.clock.now()

    # ------------------------------------------------------------ the dead-man heartbeat
    def beat(self) -> None:
        """The loop is alive (call once per tick)."""
        self._beat = self.clock.now()

    def start_heartbeat(self, urgent: Callable[[], bool]) -> None:
        """Feed the firmware's emergency-stop watchdog while beats are fresh (see the module docstring)."""
        if self._heartbeat is not None:
            return
        self._heartbeat_stop.clear()
        self.beat()
        self._heartbeat = threading.Thread(target=self._heartbeat_loop, args=(urgent,), name="deadman", daemon=True)
        self._heartbeat.start()

    def stop_heartbeat(self) -> None:
        self._heartbeat_stop.set()
        if self._heartbeat is not None:
            self._heartbeat.join(timeout=3)
            self._heartbeat = None

    def _heartbeat_loop(self, urgent: Callable[[], bool]) -> None:
        while not self._heartbeat_stop.is_set():
            if urgent() and not self.urgent_stop:
                self.urgent_stop = True
                self.emergency_stop(self.names)
            if self.clock.now() - self._beat <= self.heartbeat_timeout:
                for cf in self._cf.values():
                    with contextlib.suppress(Exception):
                        cf.supervisor.send_emergency_stop_watchdog()
                self.heartbeats += 1
            self._heartbeat_stop.wait(self.heartbeat_period / self.clock.rate)
