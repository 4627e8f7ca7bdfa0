"""A simulated Crazyflie fleet that real cflib flies over its UDP driver, behaving like the firmware.

Each simulated drone (:class:`~atdrone.deploy.simdrone.SimCrazyflie`, its firmware model)
answers on its own loopback UDP port the way a Crazyflie answers cflib
(:mod:`atdrone.deploy.crtp`): link source, protocol version, parameter and log tables of
firmware names, parameter reads and writes, log blocks streamed at their period,
supervisor state with the response bit.

``simradio://127.0.0.1:PORT`` URIs go through :class:`~atdrone.deploy.simradio.SimRadio`,
a model of the Crazyradio (one shared dongle, a one-packet send queue whose ``put``
blocks up to 2 s, a packet rate, lost tries retried); :meth:`SimFleet.jam_radio` blocks
it. ``udp://`` URIs reach the same drones without the radio model.

Dynamics run on the fleet's :class:`~atdrone.deploy.clock.Clock`. Faults:
:meth:`SimFleet.cut_link` (for good or for a while), :meth:`SimFleet.push` (wind),
:meth:`SimFleet.set_battery`, :meth:`SimFleet.jam_radio`.
"""

from __future__ import annotations

import contextlib
import math
import select
import socket
import struct
import threading
import zlib
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from atdrone.deploy import crtp
from atdrone.deploy.clock import Clock
from atdrone.deploy.simdrone import LOG_VARS, PARAMS, DroneDynamics, SimCrazyflie, _Log
from atdrone.deploy.simradio import _RADIOS, SIMRADIO, LinkLoss, SimRadio, register_simradio

__all__ = ["DroneDynamics", "SimCrazyflie", "SimFleet", "SimRadio", "register_simradio"]


def _toc_crc(entries: Sequence[tuple[Any, ...]]) -> int:
    return zlib.crc32(repr(entries).encode()) & 0xFFFFFFFF


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
        radio_loss: float = 0.05,
        radio_retries: int = 3,
        lossy: bool | None = None,
    ) -> None:
        start = np.asarray(start, dtype=np.float64).reshape(len(names), 3)
        self.clock = clock
        self.dyn = dynamics or DroneDynamics()
        self.drones = {n: SimCrazyflie(n, start[i].copy(), self.dyn, yaw=float(yaw)) for i, n in enumerate(names)}
        bias = np.random.default_rng(seed).uniform(0, 2 * math.pi, len(names))  # each IMU's bias direction
        for d, a in zip(self.drones.values(), bias, strict=True):
            d.bias_dir = np.array([math.cos(a), math.sin(a), 0.0])
        self._lock = threading.Lock()
        self._socks: dict[str, socket.socket] = {}
        self._peers: dict[str, Any] = {}
        for n in names:
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
            self._socks[n] = s
        self._taking = {n: threading.Lock() for n in names}  # one reader of a drone's socket at a time, in order
        self._poses_blocked = dict.fromkeys(names, -math.inf)  # clock time until which no pose reaches a drone
        self.radio = (  # packets per clock second
            SimRadio(packet_rate * clock.rate, loss=radio_loss, retries=radio_retries, seed=seed) if radio else None
        )
        # drone-to-host packets lost as rarely as the radio's (when the radio model sits in another process: lossy)
        self.downlink = LinkLoss(radio_loss, radio_retries, seed + 1) if (radio if lossy is None else lossy) else None
        self.on_step: Callable[[], None] | None = None  # called after every physics step (outside the lock)
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
        """Per drone: what it received (counts), what stopped its motors and when (history), locked, its true
        position and velocity, motors on, tumbled, its ground impacts (clock time, speed m/s, motors on)."""
        with self._lock:
            return {
                n: {
                    "counts": dict(d.counts),
                    "history": list(d.history),
                    "locked": d.locked,
                    "pos": d.pos.tolist(),
                    "vel": d.vel.tolist(),
                    "motors_on": d.motors_on,
                    "tumbled": d.tumbled,
                    "impacts": list(d.impacts),
                }
                for n, d in self.drones.items()
            }

    def counts(self) -> Counter[str]:
        """What the fleet received, summed over drones, by kind."""
        total: Counter[str] = Counter()
        for d in self.drones.values():
            total.update(d.counts)
        return total

    def cut_link(self, name: str, seconds: float | None = None) -> None:
        """The drone's radio link is lost, for good or for ``seconds`` (clock): it neither hears nor answers (its
        watchdogs then act)."""
        with self._lock:
            d = self.drones[name]
            d.link_cut = True
            d.link_back = np.inf if seconds is None else self.clock.now() + seconds

    def jam_radio(self, seconds: float) -> None:
        """The shared radio stops sending for ``seconds`` (wall time): every send blocks."""
        if self.radio is None:
            raise RuntimeError("this fleet has no radio model (radio=False)")
        self.radio.jam(seconds)

    def block_poses(self, name: str, seconds: float) -> None:
        """No motion-capture pose reaches the drone's estimator for ``seconds`` (clock): every other packet does
        (a ground station sending another body's stream, a localization port starved); it dead-reckons."""
        with self._lock:
            self._poses_blocked[name] = self.clock.now() + seconds

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
            # packets that reached this host before the step are the firmware's before its watchdogs judge: a
            # step of this process run late (the host busy) must not cut a drone whose keep-alive is waiting
            for n in self.drones:
                self._take(n)
            now = self.clock.now()
            with self._lock:
                for d in self.drones.values():
                    d.step(now, dt)
                due = [(n, d) for n, d in self.drones.items() if not d.link_cut and n in self._peers]
            if self.on_step is not None:
                self.on_step()
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
        if self.downlink is not None and not self.downlink.delivered():  # on an acknowledgement lost every try
            return
        with contextlib.suppress(OSError):
            self._socks[name].sendto(crtp.packet(port, channel, payload), peer)

    def _serve(self, name: str) -> None:
        sock = self._socks[name]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([sock], [], [], 0.05)
            except (OSError, ValueError):  # closed by stop()
                continue
            if ready:
                self._take(name)

    def _take(self, name: str) -> None:
        """Handle every packet waiting on the drone's socket, in the order sent."""
        with self._taking[name]:
            while True:
                try:
                    data, peer = self._socks[name].recvfrom(64)
                except OSError:  # nothing waiting (or closed)
                    return
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
            pose = ch == crtp.LOC_POSITION or (ch == crtp.LOC_GENERIC and bool(p) and p[0] == crtp.LOC_EXT_POSE)
            if pose and now < self._poses_blocked[d.name]:
                d.counts["pose_blocked"] += 1
                return []
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
