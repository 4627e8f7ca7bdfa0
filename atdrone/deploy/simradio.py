"""A model of the Crazyradio link the simulated fleet is reached through (``simradio://`` URIs).

Like cflib's radio driver over one Crazyradio: each link's send puts the packet in that
link's own queue holding one packet and waits up to ``put_timeout`` wall seconds for
room, then reports a link error; the dongle serves the links in turn, one packet every
``1 / packet_rate`` wall seconds (so no link's sender can be crowded out by the others). Each try
is lost with probability ``loss`` (no acknowledgement) and tried again, at most
``retries`` times more (the radio's automatic retries), each try costing a packet slot;
a packet whose every try was lost is dropped. Drone-to-host packets ride on the
acknowledgements and are lost as rarely (:meth:`SimRadio.delivered`). :meth:`SimRadio.jam`
stops the dongle for a while (interference, a hung USB transfer): senders block.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any

import numpy as np

SIMRADIO = "simradio://"


class LinkLoss:
    """Radio tries lost with probability ``loss``, each packet tried ``1 + retries`` times (see the module
    docstring); thread-safe."""

    def __init__(self, loss: float = 0.0, retries: int = 3, seed: int = 0) -> None:
        self.loss, self.retries = loss, retries
        self.rng = np.random.default_rng(seed)
        self.tries = 0
        self.dropped = 0
        self._draw = threading.Lock()

    def delivered(self) -> bool:
        """Whether one packet gets through (every try lost: it does not)."""
        with self._draw:
            for _ in range(self.retries + 1):
                self.tries += 1
                if self.rng.random() >= self.loss:
                    return True
            self.dropped += 1
            return False


class SimRadio(LinkLoss):
    """A Crazyradio shared by every ``simradio://`` link of a fleet: one dongle sends packets in turn.

    Like cflib's radio driver, each link's send puts the packet in the link's own queue
    holding one packet (:meth:`link_queue`) and waits up to ``put_timeout`` wall seconds for
    room, then reports a link error; the dongle takes the links' packets in turn, one every
    ``1 / packet_rate`` wall seconds. :meth:`jam` stops it for a
    while (interference, a hung USB transfer): senders block.
    """

    def __init__(
        self, packet_rate: float = 2000.0, put_timeout: float = 2.0, loss: float = 0.0, retries: int = 3, seed: int = 0
    ) -> None:
        super().__init__(loss, retries, seed)
        self.packet_rate, self.put_timeout = packet_rate, put_timeout
        self.links: list[tuple[Any, queue.Queue[Any]]] = []  # (driver, its one-packet queue), in connect order
        self.ready = threading.Event()  # a packet was queued
        self.jammed_until = 0.0
        self.sent = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="simradio", daemon=True)
        self._thread.start()

    def link_queue(self, driver: Any) -> queue.Queue[Any]:
        """A new link's queue of one packet (cflib's out_queue); the dongle serves it from now on."""
        out: queue.Queue[Any] = queue.Queue(1)
        self.links = [*self.links, (driver, out)]
        return out

    def drop_link(self, driver: Any) -> None:
        """Stop serving a closed link (a packet it left queued is not sent)."""
        self.links = [link for link in self.links if link[0] is not driver]

    def jam(self, seconds: float) -> None:
        self.jammed_until = time.monotonic() + seconds

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)

    def _run(self) -> None:
        next_t, turn = time.monotonic(), 0
        while not self._stop.is_set():
            self.ready.clear()
            links, taken = self.links, None
            for i in range(len(links)):  # the next link in turn with a packet waiting
                driver, out = links[(turn + i) % len(links)]
                try:
                    taken = driver, out.get_nowait()
                except queue.Empty:
                    continue
                turn = (turn + i + 1) % len(links)
                break
            if taken is None:
                self.ready.wait(0.05)
                continue
            driver, pk = taken
            while time.monotonic() < self.jammed_until and not self._stop.is_set():
                time.sleep(0.005)
            tries_before = self.tries
            through = self.delivered()
            now = time.monotonic()
            slots = self.tries - tries_before  # every try takes the dongle a packet's time
            next_t = max(next_t, now - 0.02) + slots / self.packet_rate  # at most 20 ms of burst credit
            if next_t > now:
                time.sleep(next_t - now)
            if through:
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
            self.out = self.radio.link_queue(self)
            super().connect(udp, stats_cb, error_cb)

        def send_packet(self, pk: Any) -> bool:
            try:
                self.out.put(pk, True, self.radio.put_timeout)
                self.radio.ready.set()
                return True
            except queue.Full:
                if self.link_error_callback:
                    self.link_error_callback("RadioDriver: Could not send packet to copter")
                return False

        def close(self) -> None:
            if hasattr(self, "radio"):
                self.radio.drop_link(self)
            super().close()

        def transmit(self, pk: Any) -> None:
            UdpDriver.send_packet(self, pk)

    cflib.crtp.CLASSES.insert(0, SimRadioDriver)
