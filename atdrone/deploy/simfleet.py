"""A simulated Crazyflie fleet that real cflib flies over its UDP driver.

Each :class:`SimCrazyflie` answers on its own loopback UDP port (``udp://127.0.0.1:PORT``)
the way a Crazyflie answers cflib (:mod:`atdrone.deploy.crtp`): the link source and
protocol version, the log and parameter TOCs, parameter reads and writes, log blocks
(``pm.vbat``, the state estimate, the supervisor bits) streamed at their period, the
memory count. It decodes what cflib sends: position and full-state setpoints, the
meta command that hands control back to the high-level commander, extpos, high-level
takeoff/land/go_to/stop, arming and emergency stop, and counts every kind.

Dynamics (:class:`DroneDynamics`), on the fleet's :class:`~atdrone.deploy.clock.Clock`:
the drone tracks its position setpoint with time constant ``tau`` (velocity command
``(target - pos) / tau``, speed and acceleration bounded); the high-level commander
flies straight lines over the commanded duration and then holds; a low-level setpoint
overrides the high-level commander until ``notify_setpoint_stop``. The firmware's
watchdogs act on low-level control only: ``level_out`` s without a setpoint the drone
levels out (no horizontal acceleration, altitude held), ``shutdown`` s the motors stop
and it falls. Motors spin only after an arming request; an emergency stop cuts them
and latches. Faults: :meth:`SimFleet.cut_link`, :meth:`SimFleet.push` (wind),
:meth:`SimFleet.set_battery`.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading
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

PARAMS: tuple[tuple[str, str, str, float], ...] = (  # group, name, type, default
    ("stabilizer", "controller", "uint8_t", 1),
    ("stabilizer", "estimator", "uint8_t", 1),
    ("locSrv", "extPosStdDev", "float", 0.01),
    ("commander", "enHighLevel", "uint8_t", 0),
    ("kalman", "resetEstimation", "uint8_t", 0),
)
LOG_VARS: tuple[tuple[str, str, str], ...] = (
    ("pm", "vbat", "float"),
    ("stateEstimate", "x", "float"),
    ("stateEstimate", "y", "float"),
    ("stateEstimate", "z", "float"),
    ("supervisor", "info", "uint16_t"),
)


@dataclass(frozen=True)
class DroneDynamics:
    """How a simulated Crazyflie flies (seconds, metres, volts)."""

    tau: float = 0.1  # time constant of tracking a position setpoint
    max_acc: float = 4.0  # m/s^2
    max_speed: float = 1.5  # m/s
    level_out: float = 0.5  # s without a low-level setpoint: level out
    shutdown: float = 2.0  # s: motors off
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
class SimCrazyflie:
    """One simulated drone: state, the tables cflib reads, and what it received."""

    name: str
    pos: np.ndarray
    dyn: DroneDynamics
    vel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw: float = float(np.pi / 2)
    armed: bool = False
    motors_on: bool = False
    locked: bool = False  # emergency stop latched
    mode: str = "idle"  # idle | hl | ll
    hl_from: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hl_to: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hl_yaw: float = float(np.pi / 2)
    hl_t0: float = 0.0
    hl_duration: float = 0.0
    hl_landing: bool = False
    target: np.ndarray | None = None
    target_yaw: float = float(np.pi / 2)
    last_setpoint: float = -np.inf
    push_acc: np.ndarray = field(default_factory=lambda: np.zeros(3))
    battery: float = 4.1
    extpos: tuple[float, float, float] | None = None
    link_cut: bool = False
    counts: Counter[str] = field(default_factory=Counter)
    params: dict[str, float] = field(default_factory=dict)
    logs: dict[int, _Log] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.battery = self.dyn.battery_start
        self.params = {f"{g}.{n}": v for g, n, _, v in PARAMS}

    # ------------------------------------------------------------ commands
    def command_hl(self, cmd: crtp.HighLevel, now: float) -> None:
        if cmd.kind == "stop":
            self.motors_on, self.mode = False, "idle"
            return
        if not (self.armed and not self.locked):
            self.counts["refused"] += 1
            return
        if self.mode == "ll":  # low-level setpoints have priority until notify_setpoint_stop
            self.counts["hl_ignored"] += 1
            return
        start = self.pos.copy()
        if cmd.kind == "takeoff" or cmd.kind == "land":
            end, yaw = np.array([start[0], start[1], cmd.target[2]]), self.yaw
        else:
            end = np.array(cmd.target) + (start if cmd.relative else 0.0)
            yaw = cmd.yaw
        self.motors_on, self.mode = True, "hl"
        self.hl_from, self.hl_to, self.hl_yaw = start, end, yaw
        self.hl_t0, self.hl_duration, self.hl_landing = now, max(cmd.duration, 1e-3), cmd.kind == "land"

    def command_setpoint(self, sp: crtp.Setpoint, now: float) -> None:
        if sp.kind == "stop":
            self.motors_on, self.mode = False, "idle"
            return
        if sp.pos is None:  # velocity/hover setpoints: Mellinger tracks x/y only from positions
            return
        if not (self.armed and not self.locked):
            self.counts["refused"] += 1
            return
        self.motors_on, self.mode = True, "ll"
        self.target = np.array(sp.pos)
        if sp.yaw_deg is not None:
            self.target_yaw = float(np.radians(sp.yaw_deg))
        self.last_setpoint = now

    def notify_stop(self, now: float) -> None:
        """Hand control back to the high-level commander, which holds where the drone is."""
        if self.mode == "ll":
            self.mode = "hl"
            self.hl_from = self.hl_to = self.pos.copy()
            self.hl_yaw, self.hl_t0, self.hl_duration, self.hl_landing = self.yaw, now, 1e-3, False

    def emergency_stop(self) -> None:
        self.motors_on, self.locked, self.armed, self.mode = False, True, False, "idle"

    # ------------------------------------------------------------ physics
    def step(self, now: float, dt: float) -> None:
        d = self.dyn
        if self.motors_on:
            self.battery -= d.battery_drain * dt
        if self.mode == "ll":
            age = now - self.last_setpoint
            if age > d.shutdown:
                self.motors_on, self.mode = False, "idle"
                self.counts["watchdog_shutdown"] += 1
            elif age > d.level_out:
                self._fly(None, 0.0, dt)  # level: coast horizontally, hold altitude
                return
        if not self.motors_on:
            if self.pos[2] > 0:
                self.vel = np.array([0.0, 0.0, self.vel[2] - GRAVITY * dt])
                self.pos = self.pos + self.vel * dt
            if self.pos[2] <= 0:
                self.pos[2], self.vel = 0.0, np.zeros(3)
            return
        if self.mode == "hl":
            s = min(1.0, (now - self.hl_t0) / self.hl_duration)
            target = self.hl_from + (self.hl_to - self.hl_from) * s
            self.target_yaw = self.hl_yaw
            if self.hl_landing and s >= 1.0 and self.pos[2] < 0.03:
                self.motors_on, self.mode = False, "idle"  # landed: the high-level commander stops the motors
                return
            self._fly(target, self.target_yaw, dt)
        elif self.mode == "ll" and self.target is not None:
            self._fly(self.target, self.target_yaw, dt)

    def _fly(self, target: np.ndarray | None, yaw: float | None, dt: float) -> None:
        d = self.dyn
        if target is None:  # levelled out: horizontal velocity kept, vertical held
            want = np.array([self.vel[0], self.vel[1], 0.0])
        else:
            want = (target - self.pos) / d.tau
            speed = float(np.linalg.norm(want))
            if speed > d.max_speed:
                want *= d.max_speed / speed
        acc = (want - self.vel) / max(dt, d.tau / 4)  # critically damped: omega 2 / tau
        norm = float(np.linalg.norm(acc))
        if norm > d.max_acc:
            acc *= d.max_acc / norm
        self.vel = self.vel + (acc + self.push_acc) * dt
        self.pos = self.pos + self.vel * dt
        if self.pos[2] < 0:
            self.pos[2], self.vel[2] = 0.0, max(0.0, self.vel[2])
        if yaw is not None:
            err = float(wrap_angle(np.array(yaw - self.yaw)))
            self.yaw = float(wrap_angle(np.array(self.yaw + err * min(1.0, dt / d.tau))))

    def supervisor_bits(self) -> int:
        return (
            (1 << 0)  # can be armed
            | (int(self.armed) << 1)
            | (int(self.armed and not self.locked) << 3)
            | (int(self.motors_on and self.pos[2] > 0.02) << 4)
            | (int(self.locked) << 6)
            | (int(self.mode == "hl") << 8)
        )

    def log_value(self, ident: int) -> float:
        group, name, _ = LOG_VARS[ident]
        if (group, name) == ("pm", "vbat"):
            return self.battery
        if group == "stateEstimate":
            return float(self.pos["xyz".index(name)])
        return float(self.supervisor_bits())


def _toc_crc(entries: Sequence[tuple[Any, ...]]) -> int:
    return zlib.crc32(repr(entries).encode()) & 0xFFFFFFFF


class SimFleet:
    """Simulated Crazyflies on loopback UDP ports, stepped on a clock (a context manager)."""

    def __init__(
        self,
        names: Sequence[str],
        start: np.ndarray,
        clock: Clock,
        dynamics: DroneDynamics | None = None,
        seed: int = 0,
    ) -> None:
        start = np.asarray(start, dtype=np.float64).reshape(len(names), 3)
        self.clock = clock
        self.dyn = dynamics or DroneDynamics()
        self.drones = {n: SimCrazyflie(n, start[i].copy(), self.dyn) for i, n in enumerate(names)}
        self._lock = threading.Lock()
        self._socks: dict[str, socket.socket] = {}
        self._peers: dict[str, Any] = {}
        for n in names:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.settimeout(0.05)
            self._socks[n] = s
        self.uris = {n: f"udp://127.0.0.1:{s.getsockname()[1]}" for n, s in self._socks.items()}
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
        for s in self._socks.values():
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

    def counts(self) -> Counter[str]:
        """What the fleet received, summed over drones, by kind."""
        total: Counter[str] = Counter()
        for d in self.drones.values():
            total.update(d.counts)
        return total

    def cut_link(self, name: str) -> None:
        """The drone's radio link is lost: it neither hears nor answers (its watchdogs then act)."""
        self.drones[name].link_cut = True

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
        if port == crtp.COMMANDER:  # legacy roll/pitch/yawrate/thrust: thrust 0 stops the motors
            d.counts["setpoint_rpyt"] += 1
            if len(p) >= 14 and struct.unpack("<fffH", p[:14])[3] == 0 and d.mode == "ll":
                d.motors_on, d.mode = False, "idle"
            return []
        if port == crtp.LOCALIZATION:
            if ch == crtp.LOC_POSITION:
                d.extpos = crtp.decode_extpos(p)
                d.counts["extpos"] += 1
            elif ch == crtp.LOC_GENERIC and p and p[0] == crtp.LOC_EXT_POSE:
                d.extpos = struct.unpack("<fff", p[1:13])
                d.counts["extpose"] += 1
            elif ch == crtp.LOC_GENERIC and p and p[0] == crtp.LOC_EMERGENCY_STOP:
                d.counts["estop"] += 1
                d.emergency_stop()
            return []
        if port == crtp.SETPOINT_HL:
            cmd = crtp.decode_high_level(p)
            d.counts[f"hl_{cmd.kind}"] += 1
            d.command_hl(cmd, now)
            return []
        if port == crtp.SUPERVISOR:
            if ch == crtp.SUPERVISOR_COMMAND and p:
                if p[0] == crtp.SUP_ARM:
                    self._arm(d, bool(p[1]) if len(p) > 1 else True)
                elif p[0] in (crtp.SUP_EMERGENCY_STOP, crtp.SUP_EMERGENCY_STOP_WATCHDOG):
                    d.counts["estop"] += 1
                    d.emergency_stop()
            elif ch == crtp.SUPERVISOR_INFO and p and p[0] == crtp.SUP_GET_STATE:
                return [(port, ch, struct.pack("<BH", crtp.SUP_GET_STATE, d.supervisor_bits()))]
            return []
        d.counts[f"port{port}"] += 1
        return []

    @staticmethod
    def _arm(d: SimCrazyflie, arm: bool) -> None:
        d.counts["arming"] += 1
        if d.locked:
            return
        d.armed = arm
        if not arm:
            d.motors_on, d.mode = False, "idle"

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
