"""The simulated Crazyflie fleet, flown by real cflib over its UDP driver, and the cflib bridge on top of it."""

from __future__ import annotations

import math
import socket
import struct
import time
from collections.abc import Iterator

import numpy as np
import pytest

from atdrone.deploy import crtp
from atdrone.deploy.bridge import BridgeError, CflibBridge
from atdrone.deploy.clock import ScaledClock
from atdrone.deploy.simfleet import DroneDynamics, SimFleet

cflib = pytest.importorskip("cflib")


@pytest.fixture
def one(tmp_path) -> Iterator[tuple[SimFleet, object]]:
    """One simulated drone at (1, 1, 0) and a cflib SyncCrazyflie connected to it (real time)."""
    import cflib.crtp
    from cflib.crazyflie import Crazyflie
    from cflib.crazyflie.syncCrazyflie import SyncCrazyflie

    cflib.crtp.init_drivers()
    with SimFleet(["a"], np.array([[1.0, 1.0, 0.0]]), ScaledClock(1.0)) as fleet:
        scf = SyncCrazyflie(fleet.uris["a"], cf=Crazyflie(rw_cache=str(tmp_path)))
        scf.open_link()
        try:
            yield fleet, scf
        finally:
            scf.close_link()


def wait_for(condition, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return False


def test_crtp_headers_and_packets() -> None:
    assert crtp.header(crtp.COMMANDER_GENERIC, 0) == 0x7C  # port 7 << 4 | 3 << 2 | 0
    assert crtp.split_header(0x7C) == (7, 0)
    with pytest.raises(ValueError, match="exceeds 30"):
        crtp.packet(crtp.LOGGING, 2, bytes(31))
    sp = crtp.decode_setpoint(struct.pack("<Bffff", crtp.SETPOINT_POSITION, 1.0, 2.0, 0.5, 90.0))
    assert sp.kind == "position" and sp.pos == (1.0, 2.0, 0.5) and sp.yaw_deg == 90.0


def test_cflib_connects_reads_the_tocs_and_sets_parameters(one) -> None:
    fleet, scf = one
    cf = scf.cf
    scf.wait_for_params()
    assert cf.param.get_value("stabilizer.controller") == "1"
    cf.param.set_value("stabilizer.controller", 2)
    cf.param.set_value("locSrv.extPosStdDev", 0.02)
    assert wait_for(lambda: fleet.drone("a").params["stabilizer.controller"] == 2)
    assert wait_for(lambda: abs(fleet.drone("a").params["locSrv.extPosStdDev"] - 0.02) < 1e-6)
    assert {e for e in cf.log.toc.toc["pm"]} == {"vbat"}


def test_what_cflib_sends_is_decoded(one) -> None:
    fleet, scf = one
    cf = scf.cf
    cf.extpos.send_extpos(1.25, -0.5, 0.75)
    assert wait_for(lambda: fleet.drone("a").extpos is not None)
    np.testing.assert_allclose(fleet.drone("a").extpos, (1.25, -0.5, 0.75), atol=1e-6)
    # setpoints before arming are refused: the motors never spin
    cf.commander.send_position_setpoint(1.0, 1.0, 0.5, 90.0)
    cf.high_level_commander.takeoff(0.5, 1.0)
    assert wait_for(lambda: fleet.drone("a").counts["refused"] == 2)
    assert not fleet.drone("a").motors_on and fleet.drone("a").counts["arming"] == 0


def test_takeoff_setpoints_watchdogs_and_emergency_stop(one) -> None:
    fleet, scf = one
    cf, d = scf.cf, fleet.drone("a")
    cf.supervisor.send_arming_request(True)
    assert wait_for(lambda: d.armed)
    cf.high_level_commander.takeoff(0.5, 1.0)
    assert wait_for(lambda: abs(d.pos[2] - 0.5) < 0.02, 3.0)
    # a position setpoint 0.4 m away: with tau 0.1 s (critically damped) the drone is within 2 cm in 1 s
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.0:
        cf.commander.send_position_setpoint(1.4, 1.0, 0.5, 0.0)
        time.sleep(0.05)
    assert abs(d.pos[0] - 1.4) < 0.02 and abs(d.yaw) < 0.05  # yaw: 0 degrees sent, radians held
    # stop streaming: level out after 0.5 s (altitude held), motors off after 2 s (it falls)
    time.sleep(1.0)
    assert d.motors_on and abs(d.pos[2] - 0.5) < 0.03
    assert wait_for(lambda: not d.motors_on, 1.5) and wait_for(lambda: d.pos[2] == 0.0, 1.0)
    assert d.counts["watchdog_shutdown"] == 1
    # the emergency stop cuts the motors and latches: arming again does nothing
    cf.supervisor.send_arming_request(True)
    cf.high_level_commander.takeoff(0.5, 1.0)
    assert wait_for(lambda: d.motors_on)
    cf.supervisor.send_emergency_stop()
    assert wait_for(lambda: d.locked and not d.motors_on)
    cf.supervisor.send_arming_request(True)
    cf.high_level_commander.takeoff(0.5, 1.0)
    time.sleep(0.2)
    assert not d.motors_on and d.counts["estop"] == 1


def test_battery_log_and_a_cut_link(one) -> None:
    from cflib.crazyflie.log import LogConfig

    fleet, scf = one
    seen: list[float] = []
    log = LogConfig(name="bat", period_in_ms=100)
    log.add_variable("pm.vbat", "float")
    scf.cf.log.add_config(log)
    log.data_received_cb.add_callback(lambda _t, data, _c: seen.append(data["pm.vbat"]))
    log.start()
    assert wait_for(lambda: len(seen) >= 2)
    fleet.set_battery("a", 3.3)
    assert wait_for(lambda: abs(seen[-1] - 3.3) < 1e-3)
    fleet.cut_link("a")
    time.sleep(0.2)
    n = len(seen)
    time.sleep(0.5)
    assert len(seen) == n  # nothing arrives over a lost link


def test_bridge_flies_three_drones_and_reports_a_lost_link(tmp_path) -> None:
    clock = ScaledClock(2.0)
    start = np.array([[0.5, 0.5, 0.0], [1.5, 0.5, 0.0], [2.5, 0.5, 0.0]])
    with SimFleet(["a", "b", "c"], start, clock, DroneDynamics()) as fleet:
        bridge = CflibBridge(fleet.uris, cache_dir=tmp_path)
        bridge.open()
        try:
            assert all(fleet.drone(n).params["stabilizer.controller"] == 2 for n in "abc")
            assert all(fleet.drone(n).params["stabilizer.estimator"] == 2 for n in "abc")
            assert wait_for(lambda: all(math.isfinite(v) for v in bridge.battery().values()))
            bridge.arm(list("abc"))
            bridge.takeoff(list("abc"), 0.5, 1.0)
            clock.sleep(1.5)
            for _ in range(10):  # 1 s of clock time streaming setpoints 0.2 m ahead in y
                bridge.send_position({n: (p[0], 0.7, 0.5, 90.0) for n, p in zip("abc", start, strict=True)})
                clock.sleep(0.1)
            for n, p in zip("abc", start, strict=True):
                np.testing.assert_allclose(fleet.drone(n).pos, [p[0], 0.7, 0.5], atol=0.03)
            fleet.cut_link("c")
            bridge.notify_stop(list("abc"))
            bridge.go_to("a", np.array([0.5, 1.0, 0.5]), math.pi / 2, 1.0)
            clock.sleep(1.2)
            assert abs(fleet.drone("a").pos[1] - 1.0) < 0.03
            bridge.land(["a", "b"], 1.0)
            clock.sleep(1.5)
            assert all(fleet.drone(n).pos[2] == 0.0 and not fleet.drone(n).motors_on for n in "ab")
            ages = bridge.link_age()
            assert ages["c"] > 0.5 > max(ages["a"], ages["b"])
            assert bridge.sent()["arming"] == 3 and fleet.counts()["notify_stop"] == 2  # c heard nothing
        finally:
            bridge.close()


def test_bridge_open_times_out_on_a_silent_port(tmp_path) -> None:
    silent = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    silent.bind(("127.0.0.1", 0))
    try:
        bridge = CflibBridge(
            {"ghost": f"udp://127.0.0.1:{silent.getsockname()[1]}"}, connect_timeout=1.0, cache_dir=tmp_path
        )
        t0 = time.monotonic()
        with pytest.raises(BridgeError, match="cannot connect ghost within 1 s"):
            bridge.open()
        assert time.monotonic() - t0 < 3.0
    finally:
        silent.close()
