"""The bridge to the drones: one protocol for the loop, implemented with cflib.

:class:`CflibBridge` drives Crazyflies through cflib (Bitcraze's library, GPLv3, the
``atdrone[deploy]`` extra, imported only when a bridge opens): ``Swarm`` with a
``CachedCfFactory``; per drone the Kalman estimator (``stabilizer.estimator`` = 2), the
Mellinger controller (``stabilizer.controller`` = 2), the external-position trust
(``locSrv.extPosStdDev``) and the high-level commander are set, and a log block streams
``pm.vbat`` every 100 ms (its packets also tell the link is alive). Radio URIs fly real
drones; ``udp://127.0.0.1:PORT`` URIs fly the simulated fleet
(:mod:`atdrone.deploy.simfleet`) through exactly the same code.

Position setpoints are streamed (Mellinger tracks x/y only from positions; velocity
setpoints make it hold), ``send_notify_setpoint_stop`` precedes every hand-over to the
high-level commander, the high-level commander takes yaw in radians and the position
setpoint in degrees. Sending never blocks: a dead link only stops answering.
"""

from __future__ import annotations

import contextlib
import math
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from atdrone.errors import UserError

MELLINGER, KALMAN = 2, 2


class BridgeError(UserError, RuntimeError):
    """A drone cannot be reached or set up."""


class Bridge(Protocol):
    """What the deploy loop needs from the drones (names in config order)."""

    names: tuple[str, ...]

    def open(self) -> None: ...

    @staticmethod
    def _confirm(name: str, cf: Any, param: str, value: float, timeout: float = 3.0) -> None:
        """Wait until the drone has acknowledged ``param`` = ``value`` (its write answer updates cflib's copy)."""
        group, key = param.split(".")
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            seen = cf.param.values.get(group, {}).get(key)
            if seen is not None and float(seen) == float(value):
                return
            time.sleep(0.01)
        raise BridgeError(f"{name}: {param} not confirmed as {value} within {timeout:g} s")

    def close(self) -> None: ...

    def battery(self) -> dict[str, float]: ...

    def link_age(self) -> dict[str, float]: ...

    def arm(self, names: Sequence[str]) -> None: ...

    def takeoff(self, names: Sequence[str], height: float, duration: float) -> None: ...

    def go_to(self, name: str, pos: np.ndarray, yaw_rad: float, duration: float) -> None: ...

    def land(self, names: Sequence[str], duration: float) -> None: ...

    def send_position(self, setpoints: Mapping[str, tuple[float, float, float, float]]) -> None: ...

    def send_extpos(self, poses: Mapping[str, tuple[float, ...]]) -> None: ...

    def notify_stop(self, names: Sequence[str]) -> None: ...

    def emergency_stop(self, names: Sequence[str]) -> None: ...

    def sent(self) -> Counter[str]: ...


class CflibBridge:
    """The bridge over cflib (see the module docstring)."""

    def __init__(
        self,
        uris: Mapping[str, str],
        extpos_std: float = 0.01,
        connect_timeout: float = 10.0,
        cache_dir: str | Path | None = None,
    ) -> None:
        self.names = tuple(uris)
        self.uris = dict(uris)
        self.extpos_std = extpos_std
        self.connect_timeout = connect_timeout
        self.cache_dir = str(cache_dir or tempfile.mkdtemp(prefix="atdrone-cflib-toc-"))
        self._cf: dict[str, Any] = {}
        self._swarm: Any = None
        self._vbat = dict.fromkeys(self.names, math.nan)
        self._heard = dict.fromkeys(self.names, -math.inf)
        self._sent: Counter[str] = Counter()
        self._lock = threading.Lock()

    # ------------------------------------------------------------ link
    def open(self) -> None:
        """Connect every drone (within ``connect_timeout``), set its parameters, start its battery log."""
        import cflib.crtp
        from cflib.crazyflie.swarm import CachedCfFactory, Swarm

        cflib.crtp.init_drivers()
        swarm = Swarm(list(self.uris.values()), factory=CachedCfFactory(rw_cache=self.cache_dir))
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

    def _setup(self, name: str, cf: Any) -> None:
        from cflib.crazyflie.log import LogConfig

        cf.packet_received.add_callback(lambda _pk, n=name: self._heard.__setitem__(n, time.monotonic()))
        self._heard[name] = time.monotonic()
        for param, value in (
            ("stabilizer.estimator", KALMAN),
            ("stabilizer.controller", MELLINGER),
            ("locSrv.extPosStdDev", self.extpos_std),
            ("commander.enHighLevel", 1),
        ):
            cf.param.set_value(param, value)
            self._sent["param"] += 1
        for param, value in (("stabilizer.estimator", KALMAN), ("stabilizer.controller", MELLINGER)):
            self._confirm(name, cf, param, value)
        log = LogConfig(name="battery", period_in_ms=100)
        log.add_variable("pm.vbat", "float")
        cf.log.add_config(log)
        log.data_received_cb.add_callback(lambda _ts, data, _cfg, n=name: self._vbat.__setitem__(n, data["pm.vbat"]))
        log.start()

    @staticmethod
    def _confirm(name: str, cf: Any, param: str, value: float, timeout: float = 3.0) -> None:
        """Wait until the drone has acknowledged ``param`` = ``value`` (its write answer updates cflib's copy)."""
        group, key = param.split(".")
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            seen = cf.param.values.get(group, {}).get(key)
            if seen is not None and float(seen) == float(value):
                return
            time.sleep(0.01)
        raise BridgeError(f"{name}: {param} not confirmed as {value} within {timeout:g} s")

    def close(self) -> None:
        """Close every link (cflib sends a zero-thrust setpoint as it closes)."""
        if self._swarm is not None:
            for scf in self._swarm._cfs.values():
                with contextlib.suppress(Exception):  # a link that is already gone
                    scf.close_link()
            self._swarm = None

    # ------------------------------------------------------------ state
    def battery(self) -> dict[str, float]:
        return dict(self._vbat)

    def link_age(self) -> dict[str, float]:
        now = time.monotonic()
        return {n: now - t for n, t in self._heard.items()}

    def sent(self) -> Counter[str]:
        with self._lock:
            return Counter(self._sent)

    def _count(self, kind: str, n: int = 1) -> None:
        with self._lock:
            self._sent[kind] += n

    # ------------------------------------------------------------ commands
    def arm(self, names: Sequence[str]) -> None:
        for n in names:
            self._cf[n].supervisor.send_arming_request(True)
        self._count("arming", len(names))

    def takeoff(self, names: Sequence[str], height: float, duration: float) -> None:
        for n in names:
            self._cf[n].high_level_commander.takeoff(height, duration)
        self._count("takeoff", len(names))

    def go_to(self, name: str, pos: np.ndarray, yaw_rad: float, duration: float) -> None:
        x, y, z = (float(v) for v in pos)
        self._cf[name].high_level_commander.go_to(x, y, z, yaw_rad, duration)
        self._count("go_to")

    def land(self, names: Sequence[str], duration: float) -> None:
        for n in names:
            self._cf[n].high_level_commander.land(0.0, duration)
        self._count("land", len(names))

    def send_position(self, setpoints: Mapping[str, tuple[float, float, float, float]]) -> None:
        for n, (x, y, z, yaw_deg) in setpoints.items():
            self._cf[n].commander.send_position_setpoint(float(x), float(y), float(z), float(yaw_deg))
        self._count("setpoint", len(setpoints))

    def send_extpos(self, poses: Mapping[str, tuple[float, ...]]) -> None:
        for n, p in poses.items():
            cf = self._cf.get(n)
            if cf is not None:
                cf.extpos.send_extpos(float(p[0]), float(p[1]), float(p[2]))
        self._count("extpos", len(poses))

    def notify_stop(self, names: Sequence[str]) -> None:
        for n in names:
            self._cf[n].commander.send_notify_setpoint_stop()
        self._count("notify_stop", len(names))

    def emergency_stop(self, names: Sequence[str]) -> None:
        for n in names:
            self._cf[n].supervisor.send_emergency_stop()
        self._count("estop", len(names))
