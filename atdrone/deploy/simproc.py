"""The simulated fleet in a process of its own, as real drones are: their firmware never waits on the host.

:class:`FleetProcess` runs a :class:`~atdrone.deploy.simfleet.SimFleet` in a child
process on the same scaled clock (the clock's origin is shared: ``perf_counter`` is one
monotonic clock for every process). The ground station reaches it exactly as before,
over loopback UDP through cflib, and through the radio model, which stays in the
ground station's process (it is the USB dongle). What a stalled, stopped or starved
ground station does to the drones then follows from the firmware's watchdogs alone,
not from the simulation stalling with it.

The parent reads the drones' true poses from shared memory (one copy after every
physics step, without a lock, so that neither process ever waits on the other) and sends faults and the final report
request down a pipe.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing
import os
import threading
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from atdrone.deploy.clock import ScaledClock
from atdrone.deploy.simdrone import DroneDynamics
from atdrone.deploy.simradio import _RADIOS, SIMRADIO, SimRadio

START_TIMEOUT = 60.0  # wall seconds for the child to import and open its ports


def _child(
    conn: Connection,
    truth: Any,
    names: list[str],
    start: np.ndarray,
    rate: float,
    origin: float,
    dynamics: DroneDynamics,
    seed: int,
    yaw: float,
    radio_loss: float,
    radio_retries: int,
) -> None:
    """The child: the fleet, its ports sent up, the true poses into ``truth``, commands from ``conn``."""
    from atdrone.deploy.simfleet import SimFleet

    # the drones are hardware of their own: whatever cores the ground station was confined to, the fleet may
    # run on any the machine allows (the kernel keeps it within its cgroup's)
    with contextlib.suppress(AttributeError, OSError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))

    clock = ScaledClock(rate, t0=origin)
    fleet = SimFleet(
        names,
        start,
        clock,
        dynamics,
        seed=seed,
        radio=False,
        yaw=yaw,
        radio_loss=radio_loss,
        radio_retries=radio_retries,
        lossy=True,
    )
    view = np.frombuffer(truth, dtype=np.float64).reshape(len(names), 4)

    def publish() -> None:  # one copy into the shared block, no lock: a reader never waits on this process
        poses = fleet.truth()
        view[:] = np.array([[*poses[n][0], poses[n][1]] for n in names])

    fleet.on_step = publish
    publish()
    with fleet:
        conn.send({n: u.rsplit(":", 1)[1] for n, u in fleet.uris.items()})
        while True:
            try:
                what, args = conn.recv()
            except (EOFError, OSError):  # the ground station went away
                return
            if what == "stop":
                return
            if what == "report":
                conn.send(fleet.report())
            else:
                getattr(fleet, what)(*args)


class FleetProcess:
    """A simulated fleet in a child process (see the module docstring); the methods the job and its faults use,
    as :class:`~atdrone.deploy.simfleet.SimFleet` has them. A context manager."""

    def __init__(
        self,
        names: Sequence[str],
        start: np.ndarray,
        clock: ScaledClock,
        dynamics: DroneDynamics | None = None,
        seed: int = 0,
        radio: bool = True,
        yaw: float = math.pi / 2,
        packet_rate: float = 1000.0,
        radio_loss: float = 0.05,
        radio_retries: int = 3,
    ) -> None:
        self.names = list(names)
        self.clock = clock
        # fork: the child starts at once and never imports the caller's main module again (spawn would); it is
        # made before cflib, the motion capture or the policies start their threads
        ctx = multiprocessing.get_context("fork")
        self._truth = ctx.RawArray("d", len(self.names) * 4)
        self._conn, child = ctx.Pipe()
        self._lock = threading.Lock()
        self._proc = ctx.Process(
            target=_child,
            args=(
                child,
                self._truth,
                self.names,
                np.asarray(start, dtype=np.float64).reshape(len(self.names), 3),
                clock.rate,
                clock.origin,
                dynamics or DroneDynamics(),
                seed,
                float(yaw),
                radio_loss,
                radio_retries,
            ),
            name="simfleet",
            daemon=True,
        )
        self.radio = (
            SimRadio(packet_rate * clock.rate, loss=radio_loss, retries=radio_retries, seed=seed) if radio else None
        )
        self.uris: dict[str, str] = {}
        self._ports: list[int] = []

    def start(self) -> FleetProcess:
        self._proc.start()
        if not self._conn.poll(START_TIMEOUT):
            self._proc.kill()
            raise RuntimeError(f"the simulated fleet did not start within {START_TIMEOUT:g} s")
        ports: dict[str, str] = self._conn.recv()
        scheme = SIMRADIO if self.radio is not None else "udp://"
        self.uris = {n: f"{scheme}127.0.0.1:{ports[n]}" for n in self.names}
        if self.radio is not None:
            for p in ports.values():
                _RADIOS[int(p)] = self.radio
                self._ports.append(int(p))
        return self

    def stop(self) -> None:
        with self._lock:
            if self._proc.is_alive():
                with contextlib.suppress(OSError):
                    self._conn.send(("stop", ()))
        self._proc.join(5)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(2)
        if self.radio is not None:
            self.radio.close()
        for p in self._ports:
            _RADIOS.pop(p, None)

    def __enter__(self) -> FleetProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _call(self, what: str, *args: Any) -> None:
        with self._lock:
            self._conn.send((what, args))

    # ------------------------------------------------------------ views and faults
    def truth(self) -> dict[str, tuple[np.ndarray, float]]:
        """True position and yaw of every drone, as of the child's last physics step."""
        view = np.frombuffer(self._truth, dtype=np.float64).reshape(len(self.names), 4).copy()
        return {n: (view[i, :3].copy(), float(view[i, 3])) for i, n in enumerate(self.names)}

    def report(self) -> dict[str, dict[str, Any]]:
        """What :meth:`SimFleet.report` says, from the child."""
        with self._lock:
            self._conn.send(("report", ()))
            if not self._conn.poll(10.0):
                raise RuntimeError("the simulated fleet did not report")
            out: dict[str, dict[str, Any]] = self._conn.recv()
            return out

    def cut_link(self, name: str, seconds: float | None = None) -> None:
        self._call("cut_link", name, seconds)

    def block_poses(self, name: str, seconds: float) -> None:
        self._call("block_poses", name, float(seconds))

    def push(self, name: str, accel: np.ndarray) -> None:
        self._call("push", name, np.asarray(accel, dtype=np.float64))

    def set_battery(self, name: str, volts: float) -> None:
        self._call("set_battery", name, float(volts))

    def jam_radio(self, seconds: float) -> None:
        if self.radio is None:
            raise RuntimeError("this fleet has no radio model (radio=False)")
        self.radio.jam(seconds)
