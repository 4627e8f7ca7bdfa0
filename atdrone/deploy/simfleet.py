"""A simulated Crazyflie fleet that real cflib flies over its UDP driver, behaving like the firmware.

Each :class:`SimCrazyflie` answers on its own loopback UDP port the way a Crazyflie
answers cflib (:mod:`atdrone.deploy.crtp`): link source, protocol version, parameter and
log tables of firmware names, parameter reads and writes, log blocks streamed at their
period, supervisor state with the response bit. The behaviour follows facts read from
crazyflie-firmware (the code is not copied):

- **Estimator** (Kalman-like, ``stabilizer.estimator`` = 2): position from ``extpos`` /
  ``extpose`` weighted by ``locSrv.extPosStdDev``; a yaw estimate that starts at
  ``kalman.initialYaw`` (0 by default) with a standard deviation of 0.01 rad and is
  corrected only by ``extpose`` (``locSrv.extQuatStdDev``); ``kalman.resetEstimation``
  restarts it (position variance 100^2 in x/y, so ``kalman.varPX`` settles only once
  extpos flows). The true attitude turns the commanded acceleration: a yaw estimate
  off by ``e`` turns every commanded acceleration by ``e`` (90 degrees: the position loop
  spirals out, as real drones flip).
- **Controller** (Mellinger's position loop, ``ctrlMel.*``): commanded acceleration
  ``(kp (p_sp - p_est) + kd (v_sp - v_est)) / mass + a_sp`` with the firmware's default
  gains (kp_xy 0.4, kd_xy 0.2, kp_z 1.25, kd_z 0.4, mass 0.027 kg), realised through a
  first-order attitude lag and bounded by the thrust. Position setpoints carry no
  velocity: tracking a setpoint one step ahead is slow; full-state setpoints feed forward.
- **Commander**: a low-level setpoint takes over from the high-level planner (stopping
  it); high-level commands that arrive while low-level setpoints stream are queued in
  the planner; ``notify_setpoint_stop`` hands over to the planner, which sends
  motors-off while it is idle. takeoff/land turn to the yaw they carry (cflib's default
  0) unless told to keep the current yaw. A legacy setpoint of zero thrust (cflib sends
  one when it closes a link) stops the motors in any mode.
- **Watchdogs**: ``level_out`` s without a low-level setpoint the drone levels out,
  ``shutdown`` s the motors stop; once an emergency-stop watchdog packet arrived, another
  must follow within ``estop_watchdog`` s or the motors stop and the drone locks.
  Emergency stop locks; arming is needed before anything spins.
- **Radio**: ``simradio://127.0.0.1:PORT`` URIs go through :class:`SimRadio`, a model of
  the Crazyradio driver (one shared dongle, a send queue of one packet whose ``put``
  blocks up to 2 s, a packet rate); :meth:`SimFleet.jam_radio` blocks it. ``udp://`` URIs
  reach the same drones without the radio model.

Dynamics run on the fleet's :class:`~atdrone.deploy.clock.Clock`. Faults:
:meth:`SimFleet.cut_link`, :meth:`SimFleet.push` (wind), :meth:`SimFleet.set_battery`,
:meth:`SimFleet.jam_radio`.
"""

from __future__ import annotations

import contextlib
import math
import queue
import socket
import struct
import threading
import time
import zlib
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from atdrone.deploy import crtp
from atdrone.deploy.clock import Clock
from atdrone.envs.kinematics import wrap_angle

GRAVITY = 9.81
SIMRADIO = "simradio://"

PARAMS: tuple[tuple[str, str, str, float], ...] = (  # group, name, type, firmware default
    ("stabilizer", "controller", "uint8_t", 1),
    ("stabilizer", "estimator", "uint8_t", 1),
    ("stabilizer", "stop", "uint8_t", 0),
    ("commander", "enHighLevel", "uint8_t", 0),
    ("locSrv", "extPosStdDev", "float", 0.01),
    ("locSrv", "extQuatStdDev", "float", 4.5e-3),
    ("kalman", "resetEstimation", "uint8_t", 0),
    ("kalman", "initialX", "float", 0.0),
    ("kalman", "initialY", "float", 0.0),
    ("kalman", "initialZ", "float", 0.0),
    ("kalman", "initialYaw", "float", 0.0),
    ("ctrlMel", "kp_xy", "float", 0.4),
    ("ctrlMel", "kd_xy", "float", 0.2),
    ("ctrlMel", "kp_z", "float", 1.25),
    ("ctrlMel", "kd_z", "float", 0.4),
    ("ctrlMel", "mass", "float", 0.027),
    ("pm", "lowVoltage", "float", 3.2),
    ("supervisor", "infdmp", "uint8_t", 0),
)
LOG_VARS: tuple[tuple[str, str, str], ...] = (
    ("pm", "vbat", "float"),
    ("pm", "state", "uint8_t"),
    ("stateEstimate", "x", "float"),
    ("stateEstimate", "y", "float"),
    ("stateEstimate", "z", "float"),
    ("stateEstimate", "vx", "float"),
    ("stateEstimate", "vy", "float"),
    ("stateEstimate", "vz", "float"),
    ("stateEstimate", "yaw", "float"),  # degrees, as the firmware logs it
    ("kalman", "varPX", "float"),
    ("kalman", "varPY", "float"),
    ("kalman", "varPZ", "float"),
    ("ctrltarget", "x", "float"),
    ("ctrltarget", "y", "float"),
    ("ctrltarget", "z", "float"),
    ("supervisor", "info", "uint16_t"),
    ("sys", "armed", "uint8_t"),
)
INITIAL_STD_XY, INITIAL_STD_Z, INITIAL_STD_YAW = 100.0, 1.0, 0.01  # the Kalman filter's initial uncertainty
PROCESS_NOISE_POS = 1e-3  # m^2/s of position variance growth between measurements
PROCESS_NOISE_YAW = 1e-5  # rad^2/s


@dataclass(frozen=True)
class DroneDynamics:
    """How a simulated Crazyflie flies (seconds, metres, volts); gains are the firmware parameters' defaults."""

    lag: float = 0.05  # s: the attitude loop's lag from commanded to realised acceleration
    max_acc_xy: float = 6.0  # m/s^2 horizontally (about 30 degrees of tilt)
    max_acc_z: float = 6.0  # m/s^2 vertically above or below hover
    yaw_tau: float = 0.2  # s: time constant of turning to the yaw setpoint
    level_out: float = 0.5  # s without a low-level setpoint: level out
    shutdown: float = 2.0  # s: motors off
    estop_watchdog: float = 1.0  # s between emergency-stop watchdog packets, once the first arrived
    battery_start: float = 4.1
    battery_drain: float = 0.002  # V/s while the motors spin
    physics_rate: float = 100.0  # Hz of clock time


@dataclass
class _Log:
    period: float  # s
    variables: list[tuple[int, int]]  # (toc id, fetch type)
    started: bool = False
    next_t: float = 0.0


@dataclass
class _Plan:
    """The high-level planner's trajectory: a smooth (minimum-jerk) line over ``duration``."""

    start: np.ndarray
    end: np.ndarray
    yaw: float | None  # None: keep the current yaw
    t0: float
    duration: float
    landing: bool = False

    def at(self, now: float) -> tuple[np.ndarray, np.ndarray, bool]:
        """Position, velocity and whether it has finished at clock time ``now``."""
        tau = min(1.0, max(0.0, (now - self.t0) / self.duration))
        s = tau**3 * (10 - 15 * tau + 6 * tau * tau)
        ds = 30 * tau**2 * (1 - tau) ** 2 / self.duration
        delta = self.end - self.start
        return self.start + delta * s, delta * ds, tau >= 1.0


def _rotate(v: np.ndarray, angle: float) -> np.ndarray:
    """(x, y) of a 3-vector turned by ``angle`` about z (z unchanged)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1], v[2]])


@dataclass
class SimCrazyflie:
    """One simulated drone: true state, estimator, commander, the tables cflib reads, and what it received."""

    name: str
    pos: np.ndarray
    dyn: DroneDynamics
    yaw: float = float(np.pi / 2)  # the true yaw (arena frame)
    vel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc: np.ndarray = field(default_factory=lambda: np.zeros(3))  # realised acceleration (lagged), no gravity
    armed: bool = False
    motors_on: bool = False
    locked: bool = False  # emergency stop latched
    mode: str = "idle"  # idle | hl (the planner flies) | ll (low-level setpoints)
    plan: _Plan | None = None
    sp_pos: np.ndarray | None = None  # the controller's current target (estimator frame)
    sp_vel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sp_acc: np.ndarray = field(default_factory=lambda: np.zeros(3))
    sp_yaw: float = float(np.pi / 2)  # target yaw in the estimator's frame
    last_setpoint: float = -np.inf
    estop_wd: float | None = None  # clock time of the last emergency-stop watchdog packet
    # the estimator: position in its own frame, its variance, and its yaw error (true yaw - estimated yaw)
    est_pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    var_pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_error: float = 0.0
    var_yaw: float = INITIAL_STD_YAW**2
    last_measure: float = -np.inf  # clock time of the last position measurement
    now: float = 0.0  # clock time of the last physics step
    push_acc: np.ndarray = field(default_factory=lambda: np.zeros(3))
    battery: float = 4.1
    extpos: tuple[float, float, float] | None = None
    link_cut: bool = False
    counts: Counter[str] = field(default_factory=Counter)
    history: list[tuple[float, str]] = field(default_factory=list)  # (clock time, what stopped the motors)
    params: dict[str, float] = field(default_factory=dict)
    logs: dict[int, _Log] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.battery = self.dyn.battery_start
        self.params = {f"{g}.{n}": v for g, n, _, v in PARAMS}
        self.reset_estimator()

    # ------------------------------------------------------------ the estimator
    @property
    def est_yaw(self) -> float:
        return float(wrap_angle(np.array(self.yaw - self.yaw_error)))

    def reset_estimator(self) -> None:
        """kalman.resetEstimation: the state restarts at the initial position and yaw parameters."""
        p = self.params
        self.est_pos = np.array([p["kalman.initialX"], p["kalman.initialY"], p["kalman.initialZ"]], dtype=np.float64)
        self.var_pos = np.array([INITIAL_STD_XY**2, INITIAL_STD_XY**2, INITIAL_STD_Z**2])
        self.yaw_error = float(wrap_angle(np.array(self.yaw - p["kalman.initialYaw"])))
        self.var_yaw = INITIAL_STD_YAW**2
        self.counts["estimator_reset"] += 1

    def measure_position(self, p: Sequence[float], now: float = 0.0) -> None:
        self.last_measure = now
        std = max(float(self.params["locSrv.extPosStdDev"]), 1e-6)
        gain = self.var_pos / (self.var_pos + std * std)
        self.est_pos = self.est_pos + gain * (np.asarray(p, dtype=np.float64) - self.est_pos)
        self.var_pos = (1 - gain) * self.var_pos

    def measure_yaw(self, yaw: float) -> None:
        std = max(float(self.params["locSrv.extQuatStdDev"]), 1e-6)
        gain = self.var_yaw / (self.var_yaw + std * std)
        innovation = float(wrap_angle(np.array(yaw - self.est_yaw)))
        self.yaw_error = float(wrap_angle(np.array(self.yaw_error - gain * innovation)))
        self.var_yaw = (1 - gain) * self.var_yaw

    def est_vel(self) -> np.ndarray:
        """The estimator's velocity: while positions arrive (the last within 0.2 s) the filter keeps it
        consistent with them (the true velocity in the frame of the positions); without them it is the IMU's,
        turned by the yaw error."""
        if self.now - self.last_measure <= 0.2:
            return self.vel.copy()
        return _rotate(self.vel, -self.yaw_error)

    # ------------------------------------------------------------ commands
    def command_hl(self, cmd: crtp.HighLevel, now: float) -> None:
        if cmd.kind == "stop":
            self.plan = None
            if self.mode == "hl":
                self.motors_on, self.mode = False, "idle"
            return
        if not (self.armed and not self.locked):
            self.counts["refused"] += 1
            return
        start = self.est_pos.copy()
        if self.plan is not None and self.mode == "hl":
            start = self.plan.at(now)[0]  # the planner continues from where its trajectory is
        if cmd.kind in ("takeoff", "land"):
            end = np.array([start[0], start[1], cmd.target[2]])
        else:
            end = np.array(cmd.target) + (start if cmd.relative else 0.0)
        yaw = None if cmd.current_yaw else float(cmd.yaw)
        self.plan = _Plan(start, end, yaw, now, max(cmd.duration, 1e-3), landing=cmd.kind == "land")
        if self.mode == "ll":
            self.counts["hl_queued"] += 1  # low-level setpoints keep priority until notify_setpoint_stop
            return
        self.mode, self.motors_on = "hl", True

    def command_setpoint(self, sp: crtp.Setpoint, now: float) -> None:
        if sp.kind == "stop":
            self.motors_on, self.mode, self.plan = False, "ll", None
            self.last_setpoint = now
            return
        if sp.pos is None:  # velocity/hover setpoints: Mellinger tracks x/y only from positions
            return
        if not (self.armed and not self.locked):
            self.counts["refused"] += 1
            return
        if self.mode != "ll":
            self.plan = None  # a low-level setpoint stops the high-level planner
        self.motors_on, self.mode = True, "ll"
        self.sp_pos = np.array(sp.pos, dtype=np.float64)
        self.sp_vel = np.array(sp.vel if sp.kind == "full_state" and sp.vel else (0.0, 0.0, 0.0))
        self.sp_acc = np.array(sp.acc if sp.acc else (0.0, 0.0, 0.0))
        if sp.yaw_deg is not None:
            self.sp_yaw = float(np.radians(sp.yaw_deg))
        self.last_setpoint = now

    def notify_stop(self, now: float) -> None:
        """Hand control to the high-level planner; an idle planner sends motors-off."""
        if self.mode == "ll":
            self.mode = "hl"
            if self.plan is None:
                self.motors_on = False
                self.counts["idle_planner_motors_off"] += 1
                self.history.append((now, "idle_planner_motors_off"))
            else:
                self.motors_on = True

    def zero_thrust(self) -> None:
        """A legacy setpoint of zero thrust (cflib's close_link): motors off in any mode."""
        self.motors_on, self.mode, self.plan = False, "idle", None

    def emergency_stop(self, now: float, why: str = "estop") -> None:
        self.counts[why] += 1
        self.history.append((now, why))
        self.motors_on, self.locked, self.armed, self.mode, self.plan = False, True, False, "idle", None

    # ------------------------------------------------------------ physics
    def step(self, now: float, dt: float) -> None:
        d = self.dyn
        self.now = now
        if self.estop_wd is not None and now - self.estop_wd > d.estop_watchdog and not self.locked:
            self.emergency_stop(now, "estop_watchdog")
        if self.motors_on:
            self.battery -= d.battery_drain * dt
        # the estimator's prediction (IMU dead reckoning) between measurements
        self.est_pos = self.est_pos + self.est_vel() * dt
        self.var_pos = self.var_pos + PROCESS_NOISE_POS * dt
        self.var_yaw = self.var_yaw + PROCESS_NOISE_YAW * dt
        levelled = False
        if self.mode == "ll" and self.motors_on:
            age = now - self.last_setpoint
            if age > d.shutdown:
                self.motors_on, self.mode = False, "idle"
                self.counts["watchdog_shutdown"] += 1
                self.history.append((now, "watchdog_shutdown"))
            elif age > d.level_out:
                levelled = True
        if not self.motors_on:
            self.acc = np.zeros(3)
            if self.pos[2] > 0:
                self.vel = np.array([0.0, 0.0, self.vel[2] - GRAVITY * dt])
                self.pos = self.pos + self.vel * dt
            if self.pos[2] <= 0:
                self.pos[2], self.vel = 0.0, np.zeros(3)
            return
        if self.mode == "hl" and self.plan is not None:
            target, target_vel, done = self.plan.at(now)
            if self.plan.yaw is not None:
                self.sp_yaw = self.plan.yaw
            if self.plan.landing and done and self.est_pos[2] < 0.05:
                self.motors_on, self.mode, self.plan = False, "idle", None  # landed: the planner stops the motors
                return
            self.sp_pos, self.sp_vel, self.sp_acc = target, target_vel, np.zeros(3)
        command = np.zeros(3) if levelled else self._position_loop()
        if levelled:  # attitude levelled: no horizontal acceleration, altitude held
            ev = self.est_vel()
            command[2] = -float(self.params["ctrlMel.kd_z"]) * ev[2] / float(self.params["ctrlMel.mass"])
        want = _rotate(command, self.yaw_error)  # the attitude loop realises it in the true frame
        self.acc = self.acc + (want - self.acc) * min(1.0, dt / d.lag)
        self.vel = self.vel + (self.acc + self.push_acc) * dt
        self.pos = self.pos + self.vel * dt
        if self.pos[2] < 0:
            self.pos[2], self.vel[2] = 0.0, max(0.0, self.vel[2])
        err = float(wrap_angle(np.array(self.sp_yaw - self.est_yaw)))
        self.yaw = float(wrap_angle(np.array(self.yaw + err * min(1.0, dt / d.yaw_tau))))

    def _position_loop(self) -> np.ndarray:
        """Mellinger's position loop on the estimate: the commanded acceleration (m/s^2, no gravity)."""
        if self.sp_pos is None:
            return np.zeros(3)
        p, m = self.params, float(self.params["ctrlMel.mass"])
        kp = np.array([p["ctrlMel.kp_xy"], p["ctrlMel.kp_xy"], p["ctrlMel.kp_z"]], dtype=np.float64)
        kd = np.array([p["ctrlMel.kd_xy"], p["ctrlMel.kd_xy"], p["ctrlMel.kd_z"]], dtype=np.float64)
        acc = (kp * (self.sp_pos - self.est_pos) + kd * (self.sp_vel - self.est_vel())) / m + self.sp_acc
        horizontal = math.hypot(acc[0], acc[1])
        if horizontal > self.dyn.max_acc_xy:
            acc[:2] *= self.dyn.max_acc_xy / horizontal
        acc[2] = float(np.clip(acc[2], -self.dyn.max_acc_z, self.dyn.max_acc_z))
        return acc

    def supervisor_bits(self) -> int:
        flying = self.motors_on and self.pos[2] > 0.02
        finished = self.plan is not None and self.plan.at(self.plan.t0 + self.plan.duration)[2]
        return (
            int(not self.locked) << crtp.BIT_CAN_BE_ARMED
            | int(self.armed) << crtp.BIT_IS_ARMED
            | int(self.armed and not self.locked) << crtp.BIT_CAN_FLY
            | int(flying) << crtp.BIT_IS_FLYING
            | int(self.locked) << crtp.BIT_LOCKED
            | int(self.mode == "hl" and self.plan is not None) << crtp.BIT_HL_ACTIVE
            | int(finished) << crtp.BIT_HL_FINISHED
            | int(self.plan is None) << crtp.BIT_HL_DISABLED
        )

    def log_value(self, ident: int) -> float:
        group, name, _ = LOG_VARS[ident]
        key = f"{group}.{name}"
        if key == "pm.vbat":
            return self.battery
        if key == "pm.state":
            return 3.0 if self.battery < self.params["pm.lowVoltage"] else 0.0
        if group == "stateEstimate" and name in ("x", "y", "z"):
            return float(self.est_pos["xyz".index(name)])
        if group == "stateEstimate" and name in ("vx", "vy", "vz"):
            return float(self.est_vel()["xyz".index(name[1])])
        if key == "stateEstimate.yaw":
            return math.degrees(self.est_yaw)
        if group == "kalman":
            return float(self.var_pos["XYZ".index(name[-1])])
        if group == "ctrltarget":
            return float(self.sp_pos["xyz".index(name)]) if self.sp_pos is not None else 0.0
        if key == "sys.armed":
            return float(self.armed)
        return float(self.supervisor_bits())


def _toc_crc(entries: Sequence[tuple[Any, ...]]) -> int:
    return zlib.crc32(repr(entries).encode()) & 0xFFFFFFFF


class SimRadio:
    """A Crazyradio shared by every ``simradio://`` link of a fleet: one dongle sends packets in turn.

    Like cflib's radio driver, each send puts the packet in a queue holding one packet and
    waits up to ``put_timeout`` wall seconds for room, then reports a link error; the
    dongle takes one packet every ``1 / packet_rate`` wall seconds. :meth:`jam` stops it for a
    while (interference, a hung USB transfer): senders block.
    """

    def __init__(self, packet_rate: float = 2000.0, put_timeout: float = 2.0) -> None:
        self.packet_rate, self.put_timeout = packet_rate, put_timeout
        self.queue: queue.Queue[tuple[Any, Any]] = queue.Queue(1)
        self.jammed_until = 0.0
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="simradio", daemon=True)
        self._thread.start()

    def jam(self, seconds: float) -> None:
        self.jammed_until = time.monotonic() + seconds

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)

    def _run(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            try:
                driver, pk = self.queue.get(timeout=0.05)
            except queue.Empty:
                continue
            while time.monotonic() < self.jammed_until and not self._stop.is_set():
                time.sleep(0.005)
            now = time.monotonic()
            next_t = max(next_t, now - 0.02) + 1.0 / self.packet_rate  # at most 20 ms of burst credit
            if next_t > now:
                time.sleep(next_t - now)
            driver.transmit(pk)
            self.sent += 1


_RADIOS: dict[int, SimRadio] = {}  # UDP port -> the radio of its fleet


def register_simradio() -> None:
    """Make cflib open ``simradio://HOST:PORT`` URIs through the radio model (idempotent; after init_drivers)."""
    import cflib.crtp
    from cflib.crtp.exceptions import WrongUriType
    from cflib.crtp.udpdriver import UdpDriver

    if any(getattr(c, "SIMRADIO", False) for c in cflib.crtp.CLASSES):
        return

    class SimRadioDriver(UdpDriver):  # type: ignore[misc]
        SIMRADIO = True

        def connect(self, uri: str, stats_cb: Any, error_cb: Any) -> None:
            if not uri.startswith(SIMRADIO):
                raise WrongUriType("Not a simradio URI")
            udp = "udp://" + uri[len(SIMRADIO) :]
            self.radio = _RADIOS[int(udp.rsplit(":", 1)[1])]
            super().connect(udp, stats_cb, error_cb)

        def send_packet(self, pk: Any) -> bool:
            try:
                self.radio.queue.put((self, pk), True, self.radio.put_timeout)
                return True
            except queue.Full:
                if self.link_error_callback:
                    self.link_error_callback("RadioDriver: Could not send packet to copter")
                return False

        def transmit(self, pk: Any) -> None:
            UdpDriver.send_packet(self, pk)

    cflib.crtp.CLASSES.insert(0, SimRadioDriver)


class SimFleet:
    """Simulated Crazyflies on loopback UDP ports, stepped on a clock (a context manager).

    ``radio``: the URIs in :attr:`uris` are ``simradio://`` (through one :class:`SimRadio`
    taking ``packet_rate`` packets per clock second, about what a Crazyradio delivers) when
    true, plain ``udp://`` otherwise. ``yaw``: the drones' true yaw on the ground.
    """

    def __init__(
        self,
        names: Sequence[str],
        start: np.ndarray,
        clock: Clock,
        dynamics: DroneDynamics | None = None,
        seed: int = 0,
        radio: bool = True,
        yaw: float = math.pi / 2,
        packet_rate: float = 1000.0,
    ) -> None:
        start = np.asarray(start, dtype=np.float64).reshape(len(names), 3)
        self.clock = clock
        self.dyn = dynamics or DroneDynamics()
        self.drones = {n: SimCrazyflie(n, start[i].copy(), self.dyn, yaw=float(yaw)) for i, n in enumerate(names)}
        self._lock = threading.Lock()
        self._socks: dict[str, socket.socket] = {}
        self._peers: dict[str, Any] = {}
        for n in names:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.settimeout(0.05)
            self._socks[n] = s
        self.radio = SimRadio(packet_rate * clock.rate) if radio else None  # packets per clock second
        scheme = SIMRADIO if radio else "udp://"
        self.uris = {n: f"{scheme}127.0.0.1:{s.getsockname()[1]}" for n, s in self._socks.items()}
        if self.radio is not None:
            for s in self._socks.values():
                _RADIOS[s.getsockname()[1]] = self.radio
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._param_crc = _toc_crc(PARAMS)
        self._log_crc = _toc_crc(LOG_VARS)

    # ------------------------------------------------------------ lifecycle
    def start(self) -> SimFleet:
        if self._threads:
            return self
        for n in self.drones:
            t = threading.Thread(target=self._serve, args=(n,), name=f"simcf-{n}", daemon=True)
            t.start()
            self._threads.append(t)
        t = threading.Thread(target=self._physics, name="simcf-physics", daemon=True)
        t.start()
        self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self._threads = []
        if self.radio is not None:
            self.radio.close()
        for s in self._socks.values():
            _RADIOS.pop(s.getsockname()[1], None)
            s.close()

    def __enter__(self) -> SimFleet:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ------------------------------------------------------------ views and faults
    def drone(self, name: str) -> SimCrazyflie:
        return self.drones[name]

    def truth(self) -> dict[str, tuple[np.ndarray, float]]:
        """True position and yaw of every drone (for the simulated motion capture)."""
        with self._lock:
            return {n: (d.pos.copy(), d.yaw) for n, d in self.drones.items()}

    def report(self) -> dict[str, dict[str, Any]]:
        """Per drone: what it received (counts), what stopped its motors and when (history), locked, position."""
        with self._lock:
            return {
                n: {"counts": dict(d.counts), "history": list(d.history), "locked": d.locked, "pos": d.pos.tolist()}
                for n, d in self.drones.items()
            }

    def counts(self) -> Counter[str]:
        """What the fleet received, summed over drones, by kind."""
        total: Counter[str] = Counter()
        for d in self.drones.values():
            total.update(d.counts)
        return total

    def cut_link(self, name: str) -> None:
        """The drone's radio link is lost: it neither hears nor answers (its watchdogs then act)."""
        self.drones[name].link_cut = True

    def jam_radio(self, seconds: float) -> None:
        """The shared radio stops sending for ``seconds`` (wall time): every send blocks."""
        if self.radio is None:
            raise RuntimeError("this fleet has no radio model (radio=False)")
        self.radio.jam(seconds)

    def push(self, name: str, accel: np.ndarray) -> None:
        """A wind push: an extra acceleration (3,) m/s^2 on the drone while its motors spin."""
        with self._lock:
            self.drones[name].push_acc = np.asarray(accel, dtype=np.float64).reshape(3)

    def set_battery(self, name: str, volts: float) -> None:
        with self._lock:
            self.drones[name].battery = float(volts)

    # ------------------------------------------------------------ threads
    def _physics(self) -> None:
        dt = 1.0 / self.dyn.physics_rate
        t = self.clock.now()
        while not self._stop.is_set():
            t += dt
            self.clock.sleep_until(t)
            now = self.clock.now()
            with self._lock:
                for d in self.drones.values():
                    d.step(now, dt)
                due = [(n, d) for n, d in self.drones.items() if not d.link_cut and n in self._peers]
            for n, d in due:
                for block_id, log in list(d.logs.items()):
                    if log.started and now >= log.next_t:
                        log.next_t = now + log.period
                        with self._lock:
                            values = [(fetch, d.log_value(ident)) for ident, fetch in log.variables]
                        self._send(n, crtp.LOGGING, crtp.LOG_DATA, crtp.log_data(block_id, int(now * 1000), values))

    def _send(self, name: str, port: int, channel: int, payload: bytes) -> None:
        peer = self._peers.get(name)
        if peer is None or self.drones[name].link_cut:
            return
        with contextlib.suppress(OSError):
            self._socks[name].sendto(crtp.packet(port, channel, payload), peer)

    def _serve(self, name: str) -> None:
        sock = self._socks[name]
        while not self._stop.is_set():
            try:
                data, peer = sock.recvfrom(64)
            except (TimeoutError, OSError):
                continue
            d = self.drones[name]
            if d.link_cut or not data:
                continue
            self._peers[name] = peer
            port, channel = crtp.split_header(data[0])
            with self._lock:
                replies = self._handle(d, port, channel, data[1:])
            for reply in replies:
                self._send(name, *reply)

    # ------------------------------------------------------------ the protocol
    def _handle(self, d: SimCrazyflie, port: int, ch: int, p: bytes) -> list[tuple[int, int, bytes]]:
        """Decode one packet; return the answers (port, channel, payload)."""
        now = self.clock.now()
        if port == crtp.LINKCTRL:
            if ch == crtp.LINK_SOURCE:
                return [(port, ch, crtp.LINK_SOURCE_NAME)]
            return [(port, ch, p)]  # echo (and the null packet)
        if port == crtp.PLATFORM:
            if ch == crtp.PLATFORM_VERSION and p and p[0] == crtp.VERSION_GET_PROTOCOL:
                return [(port, ch, bytes([crtp.VERSION_GET_PROTOCOL, crtp.PROTOCOL_VERSION]))]
            if ch == crtp.PLATFORM_VERSION and p and p[0] == crtp.VERSION_GET_FIRMWARE:
                return [(port, ch, bytes([crtp.VERSION_GET_FIRMWARE]) + b"sim")]
            if ch == crtp.PLATFORM_COMMAND and p and p[0] == crtp.PLATFORM_REQUEST_ARMING:
                self._arm(d, bool(p[1]))
            return []
        if port == crtp.MEM:
            if ch == crtp.MEM_INFO and p and p[0] == crtp.MEM_INFO_NBR:
                return [(port, ch, bytes([crtp.MEM_INFO_NBR, 0]))]
            return []
        if port == crtp.PARAM:
            return self._param(d, ch, p)
        if port == crtp.LOGGING:
            return self._log(d, ch, p)
        if port == crtp.COMMANDER_GENERIC:
            if ch == crtp.GENERIC_SETPOINT:
                sp = crtp.decode_setpoint(p)
                d.counts[f"setpoint_{sp.kind}"] += 1
                d.command_setpoint(sp, now)
            elif ch == crtp.GENERIC_META and p and p[0] == crtp.META_NOTIFY_SETPOINT_STOP:
                d.counts["notify_stop"] += 1
                d.notify_stop(now)
            return []
        if port == crtp.COMMANDER:  # legacy roll/pitch/yawrate/thrust: thrust 0 stops the motors in any mode
            d.counts["setpoint_rpyt"] += 1
            if len(p) >= 14 and struct.unpack("<fffH", p[:14])[3] == 0:
                d.zero_thrust()
            return []
        if port == crtp.LOCALIZATION:
            return self._localization(d, ch, p, now)
        if port == crtp.SETPOINT_HL:
            cmd = crtp.decode_high_level(p)
            d.counts[f"hl_{cmd.kind}"] += 1
            d.command_hl(cmd, now)
            return []
        if port == crtp.SUPERVISOR:
            return self._supervisor(d, ch, p, now)
        d.counts[f"port{port}"] += 1
        return []

    @staticmethod
    def _localization(d: SimCrazyflie, ch: int, p: bytes, now: float) -> list[tuple[int, int, bytes]]:
        if ch == crtp.LOC_POSITION:
            d.extpos = crtp.decode_extpos(p)
            d.counts["extpos"] += 1
            d.measure_position(d.extpos, now)
        elif ch == crtp.LOC_GENERIC and p and p[0] == crtp.LOC_EXT_POSE:
            pos, quat = crtp.decode_extpose(p)
            d.extpos = pos
            d.counts["extpose"] += 1
            d.measure_position(pos, now)
            d.measure_yaw(crtp.yaw_of_quaternion(*quat))
        elif ch == crtp.LOC_GENERIC and p and p[0] == crtp.LOC_EMERGENCY_STOP:
            d.emergency_stop(now)
        elif ch == crtp.LOC_GENERIC and p and p[0] == crtp.LOC_EMERGENCY_STOP + 1:  # the legacy watchdog packet
            d.counts["estop_keepalive"] += 1
            d.estop_wd = now
        return []

    def _supervisor(self, d: SimCrazyflie, ch: int, p: bytes, now: float) -> list[tuple[int, int, bytes]]:
        port = crtp.SUPERVISOR
        if ch == crtp.SUPERVISOR_COMMAND and p:
            if p[0] == crtp.SUP_ARM:
                self._arm(d, bool(p[1]) if len(p) > 1 else True)
                return [(port, ch, bytes([crtp.SUP_ARM | crtp.SUP_RESPONSE, int(not d.locked), int(d.armed)]))]
            if p[0] == crtp.SUP_EMERGENCY_STOP:
                d.emergency_stop(now)
            elif p[0] == crtp.SUP_EMERGENCY_STOP_WATCHDOG:  # a keep-alive, not a stop
                d.counts["estop_keepalive"] += 1
                d.estop_wd = now
        elif ch == crtp.SUPERVISOR_INFO and p and p[0] == crtp.SUP_GET_STATE:
            return [(port, ch, struct.pack("<BH", crtp.SUP_GET_STATE | crtp.SUP_RESPONSE, d.supervisor_bits()))]
        return []

    @staticmethod
    def _arm(d: SimCrazyflie, arm: bool) -> None:
        d.counts["arming"] += 1
        if d.locked:
            return
        d.armed = arm
        if not arm:
            d.motors_on, d.mode, d.plan = False, "idle", None

    def _param(self, d: SimCrazyflie, ch: int, p: bytes) -> list[tuple[int, int, bytes]]:
        port = crtp.PARAM
        if ch == crtp.TOC_CHANNEL:
            if p[0] == crtp.TOC_INFO_V2:
                return [(port, ch, crtp.toc_info(len(PARAMS), self._param_crc))]
            if p[0] == crtp.TOC_ITEM_V2:
                ident = struct.unpack("<H", p[1:3])[0]
                g, n, t, _ = PARAMS[ident]
                return [(port, ch, crtp.toc_entry(ident, crtp.PARAM_TYPES[t][0], g, n))]
            return []
        ident = struct.unpack("<H", p[:2])[0]
        if ident >= len(PARAMS):
            return []
        g, n, t, _ = PARAMS[ident]
        fmt = crtp.PARAM_TYPES[t][1]
        key = f"{g}.{n}"
        if ch == crtp.PARAM_WRITE:
            d.params[key] = struct.unpack(fmt, p[2 : 2 + struct.calcsize(fmt)])[0]
            d.counts["param_write"] += 1
            if key == "kalman.resetEstimation" and d.params[key]:
                d.reset_estimator()
            return [(port, ch, p[:2] + struct.pack(fmt, d.params[key]))]
        if ch == crtp.PARAM_READ:
            value = d.params[key] if fmt == "<f" else int(d.params[key])
            return [(port, ch, p[:2] + b"\0" + struct.pack(fmt, value))]
        return []

    def _log(self, d: SimCrazyflie, ch: int, p: bytes) -> list[tuple[int, int, bytes]]:
        port = crtp.LOGGING
        if ch == crtp.TOC_CHANNEL:
            if p[0] == crtp.TOC_INFO_V2:
                return [(port, ch, crtp.toc_info(len(LOG_VARS), self._log_crc))]
            if p[0] == crtp.TOC_ITEM_V2:
                ident = struct.unpack("<H", p[1:3])[0]
                g, n, t = LOG_VARS[ident]
                return [(port, ch, crtp.toc_entry(ident, crtp.LOG_TYPE_CODE[t], g, n))]
            return []
        if ch != crtp.LOG_SETTINGS or not p:
            return []
        cmd = p[0]
        if cmd == crtp.LOG_RESET:
            d.logs.clear()
            return [(port, ch, bytes([cmd, 0, 0]))]
        block = p[1]
        if cmd in (crtp.LOG_CREATE_V2, crtp.LOG_APPEND_V2):
            items = [struct.unpack("<BH", p[i : i + 3]) for i in range(2, len(p) - 2, 3)]
            variables = [(ident, byte & 0x0F) for byte, ident in items]
            if cmd == crtp.LOG_CREATE_V2:
                d.logs[block] = _Log(period=0.1, variables=variables)
            elif block in d.logs:
                d.logs[block].variables += variables
            return [(port, ch, bytes([cmd, block, 0]))]
        if cmd == crtp.LOG_START and block in d.logs:
            d.logs[block].period = max(p[2], 1) / 100.0
            d.logs[block].started, d.logs[block].next_t = True, 0.0
            return [(port, ch, bytes([cmd, block, 0]))]
        if cmd == crtp.LOG_STOP and block in d.logs:
            d.logs[block].started = False
            return [(port, ch, bytes([cmd, block, 0]))]
        if cmd == crtp.LOG_DELETE:
            d.logs.pop(block, None)
            return [(port, ch, bytes([cmd, block, 0]))]
        return [(port, ch, bytes([cmd, block, 2]))]  # ENOENT
