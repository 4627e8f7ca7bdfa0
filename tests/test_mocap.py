"""Motion capture: the mocap-to-arena transform, the motioncapture package's mock backend, SimMocap.

SimMocap runs on scaled clocks (10-20 clock seconds per wall second) so each check
takes a fraction of a second of wall time.
"""

from __future__ import annotations

import itertools
import math
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atdrone.config import ConfigError, parse_document
from atdrone.deploy.clock import ScaledClock
from atdrone.deploy.mocap import (
    FrameTransform,
    MocapError,
    MotionCaptureSource,
    Pose,
    SimMocap,
)
from atdrone.envs.kinematics import wrap_angle


def _proper_axes() -> list[tuple[str, ...]]:
    """Every signed permutation of the mocap axes that is a rotation (determinant +1)."""
    out = []
    for perm in itertools.permutations("xyz"):
        for signs in itertools.product(("", "-"), repeat=3):
            m = np.array([[(-1.0 if s else 1.0) * (a == c) for c in "xyz"] for s, a in zip(signs, perm, strict=True)])
            if np.linalg.det(m) > 0:
                out.append(tuple(s + a for s, a in zip(signs, perm, strict=True)))
    return out


PROPER_AXES = _proper_axes()


def yaw_quat(yaw: float, axis: str = "z") -> np.ndarray:
    """The quaternion (w, x, y, z) of a rotation by ``yaw`` about a mocap axis."""
    q = np.zeros(4)
    q[0] = math.cos(yaw / 2)
    q[1 + "xyz".index(axis)] = math.sin(yaw / 2)
    return q


# ---------------------------------------------------------------- the transform
def test_there_are_24_right_handed_axis_specs() -> None:
    assert len(PROPER_AXES) == 24 and ("-y", "x", "z") in PROPER_AXES and ("y", "x", "z") not in PROPER_AXES


@settings(max_examples=150, deadline=None)
@given(
    axes=st.sampled_from(PROPER_AXES),
    origin=st.tuples(*[st.floats(-10, 10)] * 3),
    offset=st.floats(-720, 720),
    pos=st.lists(st.tuples(*[st.floats(-20, 20)] * 3), min_size=1, max_size=6),
    data=st.data(),
)
def test_to_arena_inverts_to_mocap(axes, origin, offset, pos, data) -> None:
    frame = FrameTransform(origin=origin, axes=axes, yaw_offset_deg=offset)
    yaw = np.array(data.draw(st.lists(st.floats(-10, 10), min_size=len(pos), max_size=len(pos))))
    p = np.array(pos)
    mocap, quat = frame.to_mocap(p, yaw)
    assert np.allclose(np.linalg.norm(quat, axis=1), 1.0)
    back, back_yaw = frame.to_arena(mocap, quat)
    assert np.allclose(back, p, atol=1e-9)
    assert np.allclose(wrap_angle(back_yaw - yaw), 0.0, atol=1e-9)
    assert ((back_yaw >= -math.pi) & (back_yaw < math.pi)).all()


def test_hand_computed_axes_and_origin() -> None:
    swapped = FrameTransform(axes=("-y", "x", "z"))  # arena x = -mocap y, arena y = mocap x
    pos, yaw = swapped.to_arena(np.array([[1.0, 2.0, 3.0]]), np.array([[1.0, 0.0, 0.0, 0.0]]))
    assert np.allclose(pos, [[-2.0, 1.0, 3.0]])
    assert yaw[0] == pytest.approx(math.pi / 2)  # the mocap +x axis is the arena's +y
    _, yaw = swapped.to_arena(np.zeros((1, 3)), yaw_quat(math.radians(30))[None])
    assert yaw[0] == pytest.approx(math.radians(120))
    shifted = FrameTransform(origin=(1.0, 1.0, 0.0), axes=("-y", "x", "z"))
    pos, _ = shifted.to_arena(np.array([[1.0, 2.0, 3.0]]), np.array([[1.0, 0.0, 0.0, 0.0]]))
    assert np.allclose(pos, [[-1.0, 0.0, 3.0]])
    # a Y-up system (OptiTrack's default): arena (x, y, z) = mocap (x, -z, y); yaw is about mocap +y
    y_up = FrameTransform(axes=("x", "-z", "y"))
    pos, yaw = y_up.to_arena(np.array([[1.0, 2.0, 3.0]]), yaw_quat(0.4, "y")[None])
    assert np.allclose(pos, [[1.0, -3.0, 2.0]])
    assert yaw[0] == pytest.approx(0.4)


def test_yaw_offset_is_added_to_the_mocap_yaw() -> None:
    frame = FrameTransform(yaw_offset_deg=90.0)
    _, yaw = frame.to_arena(np.zeros((2, 3)), np.stack([yaw_quat(0.0), yaw_quat(math.radians(100))]))
    assert np.allclose(yaw, [math.pi / 2, math.radians(190) - 2 * math.pi])
    _, quat = frame.to_mocap(np.zeros((1, 3)), np.array([math.pi / 2]))
    assert np.allclose(np.abs(quat), [[1.0, 0.0, 0.0, 0.0]])  # arena yaw 90 = the body's x-axis on mocap +x


def test_bad_axes_are_rejected_with_the_json_path() -> None:
    with pytest.raises(ConfigError, match=r"left-handed.*flip the sign of one axis, e.g. \['-y', 'x', 'z'\]"):
        FrameTransform(axes=("y", "x", "z"))
    with pytest.raises(ConfigError, match="exactly once"):
        FrameTransform(axes=("x", "x", "z"))
    with pytest.raises(ConfigError, match="signed mocap axis"):
        FrameTransform(axes=("x", "up", "z"))
    with pytest.raises(ConfigError, match=r"^frame\.axes: .*left-handed"):
        parse_document(FrameTransform, {"axes": ["x", "y", "-z"]}, "frame")
    parsed = parse_document(FrameTransform, {"origin": [1, 2, 0], "axes": ["-y", "x", "z"]}, "frame")
    assert parsed == FrameTransform(origin=(1.0, 2.0, 0.0), axes=("-y", "x", "z"))


# ---------------------------------------------------------------- the motioncapture package
def test_motioncapture_mock_backend_poses_in_the_arena_frame() -> None:
    clock = ScaledClock(1.0)
    bodies = "cf1(1,2,3,1,0,0,0);cf2(0.5,0.5,0.3,0.7071068,0,0,0.7071068);other(0,0,0,1,0,0,0)"
    source = MotionCaptureSource(
        "mock",
        {"rigid_bodies": bodies, "frequency": "100"},
        ["cf1", "cf2"],
        FrameTransform(axes=("-y", "x", "z")),
        clock,
    )
    seen: list[dict[str, Pose]] = []
    source.on_frame(seen.append)
    source.start()
    try:
        deadline = time.perf_counter() + 5.0
        while source.frames < 5 and time.perf_counter() < deadline:
            time.sleep(0.02)
        latest = source.latest()
    finally:
        source.stop()
    assert source.frames >= 5 and len(seen) >= 5 and not source.error
    assert set(latest) == {"cf1", "cf2"}  # only the bodies asked for
    assert np.allclose(latest["cf1"].pos, [-2.0, 1.0, 3.0]) and latest["cf1"].yaw == pytest.approx(math.pi / 2)
    assert np.allclose(latest["cf2"].pos, [-0.5, 0.5, 0.3], atol=1e-6)
    assert latest["cf2"].yaw == pytest.approx(math.pi, abs=1e-5) or latest["cf2"].yaw == pytest.approx(-math.pi)
    assert 0 < clock.now() - latest["cf1"].t < 1.0  # timed on arrival, on our clock


@pytest.mark.parametrize(
    ("kind", "cfg", "match"),
    [
        ("vicon", {"hostname": "127.0.0.1"}, r"vicon motion capture at 127\.0\.0\.1: no connection within 0\.5 s"),
        ("qualisys", {"hostname": "127.0.0.1"}, r"qualisys motion capture at 127\.0\.0\.1: .*QTM"),
        ("fzmotion", {}, r"unknown motion-capture type 'fzmotion'.*vicon, optitrack"),
    ],
    ids=["timeout", "refused", "unknown-kind"],
)
def test_connect_failures_raise_mocap_error_quickly(kind: str, cfg: dict[str, str], match: str) -> None:
    source = MotionCaptureSource(kind, cfg, [], FrameTransform(), ScaledClock(), connect_timeout=0.5)
    started = time.perf_counter()
    with pytest.raises(MocapError, match=match):
        source.start()
    assert time.perf_counter() - started < 5.0
    source.stop()  # harmless after a failed start


# ---------------------------------------------------------------- simulated motion capture
class Walker:
    """Truth for SimMocap: body "a" walks along x at 1 m/s of clock time, "b" and "c" stand still."""

    def __init__(self, clock: ScaledClock) -> None:
        self.clock = clock

    def __call__(self) -> dict[str, tuple[np.ndarray, float]]:
        t = self.clock.now()
        return {"a": (np.array([t, 1.0, 0.5]), 0.3), "b": (np.array([2.0, 3.0, 0.5]), -1.0), "c": (np.ones(3), 0.0)}


def collect(mocap: SimMocap) -> list[dict[str, Pose]]:
    frames: list[dict[str, Pose]] = []
    lock = threading.Lock()

    def keep(poses: dict[str, Pose]) -> None:
        with lock:
            frames.append(poses)

    mocap.on_frame(keep)
    return frames


def run_for(mocap: SimMocap, clock: ScaledClock, seconds: float) -> None:
    mocap.start()
    try:
        clock.sleep(seconds)
    finally:
        mocap.stop()


def test_sim_mocap_noise_and_latency() -> None:
    clock = ScaledClock(5.0)
    frame = FrameTransform(origin=(0.5, -1.0, 0.0), axes=("y", "-x", "z"), yaw_offset_deg=20.0)
    mocap = SimMocap(Walker(clock), frame, clock, rate=100.0, noise=0.01, latency=0.05, seed=1)
    frames = collect(mocap)
    run_for(mocap, clock, 3.0)
    b = np.array([f["b"].pos for f in frames])
    assert len(b) > 150
    assert np.allclose(b.mean(0), [2.0, 3.0, 0.5], atol=0.005)
    assert np.all((b.std(0) > 0.008) & (b.std(0) < 0.0125)), b.std(0)
    assert np.allclose([f["b"].yaw for f in frames], -1.0)  # no yaw noise
    # "a" moves 1 m per clock second: its arrival time minus its measured x is the latency
    lag = np.array([f["a"].t - f["a"].pos[0] for f in frames])
    assert 0.045 < np.median(lag) < 0.075, np.median(lag)


def test_mismatched_config_frame_shows_in_the_poses() -> None:
    clock = ScaledClock(10.0)
    true = FrameTransform(axes=("-y", "x", "z"))
    mocap = SimMocap(Walker(clock), FrameTransform(), clock, noise=0.0, latency=0.0, true_transform=true)
    run_for(mocap, clock, 0.3)
    b = mocap.latest()["b"]
    # the config believes mocap = arena: it reports the true frame's mocap coordinates
    assert np.allclose(b.pos, [3.0, -2.0, 0.5]) and b.yaw == pytest.approx(-1.0 - math.pi / 2)


def started(mocap: SimMocap, clock: ScaledClock) -> float:
    """Start ``mocap`` and wait for its first frame; the clock time then."""
    mocap.start()
    deadline = time.perf_counter() + 5.0
    while mocap.frames == 0 and time.perf_counter() < deadline:
        time.sleep(0.001)
    assert mocap.frames > 0
    return clock.now()


def test_one_body_dropped_ages_while_the_others_stay_fresh() -> None:
    clock = ScaledClock(5.0)
    mocap = SimMocap(Walker(clock), FrameTransform(), clock, noise=0.0, latency=0.0)
    try:
        t0 = started(mocap, clock)
        mocap.drop("b", t0 + 0.5, t0 + 2.0)
        samples = []
        for t in (0.3, 1.0, 1.8, 2.5):
            clock.sleep_until(t0 + t)
            now, latest = clock.now(), mocap.latest()
            samples.append((now, {n: now - p.t for n, p in latest.items()}))
    finally:
        mocap.stop()
    for _, ages in samples:
        assert ages["a"] < 0.25 and ages["c"] < 0.25, ages
    (_, before), (now1, during1), (now2, during2), (_, after) = samples
    assert before["b"] < 0.25 and after["b"] < 0.25
    # silent since t0 + 0.5: the age is the time since then
    for now, ages in ((now1, during1), (now2, during2)):
        assert now - (t0 + 0.5) - 0.02 < ages["b"] < now - (t0 + 0.5) + 0.25, (now - t0, ages)
    assert during2["b"] > during1["b"] + 0.5


def test_whole_system_drop_sends_no_frames_in_the_window() -> None:
    clock = ScaledClock(5.0)
    mocap = SimMocap(Walker(clock), FrameTransform(), clock, noise=0.0, latency=0.0)
    frames = collect(mocap)
    try:
        t0 = started(mocap, clock)
        mocap.drop(None, t0 + 0.5, t0 + 1.5)
        clock.sleep_until(t0 + 2.0)
    finally:
        mocap.stop()
    t = np.array([next(iter(f.values())).t for f in frames]) - t0
    assert not ((t > 0.6) & (t < 1.5)).any(), t[(t > 0.5) & (t < 1.5)]
    assert ((t < 0.5).sum() > 30) and ((t > 1.5).sum() > 30)
    assert mocap.frames == len(frames)


def test_random_dropout_leaves_bodies_out_of_frames() -> None:
    clock = ScaledClock(10.0)
    mocap = SimMocap(Walker(clock), FrameTransform(), clock, noise=0.0, latency=0.0, dropout=0.3, seed=3)
    frames = collect(mocap)
    run_for(mocap, clock, 3.0)
    present = np.array([[n in f for n in "abc"] for f in frames])
    assert len(frames) > 150 and np.allclose(present.mean(0), 0.7, atol=0.08), present.mean(0)


def test_scaled_clock_runs_the_frame_rate_in_clock_time() -> None:
    clock = ScaledClock(10.0)
    mocap = SimMocap(Walker(clock), FrameTransform(), clock, rate=100.0, noise=0.0, latency=0.0)
    begun, started = clock.now(), time.perf_counter()
    run_for(mocap, clock, 3.0)  # 3 clock seconds: 300 frames in 0.3 wall seconds
    wall, stopped = time.perf_counter() - started, clock.now()
    assert wall < 1.5  # 0.3 s, with room for a loaded host; at clock rate 1 it would take 3 s
    # a frame every 10 ms of clock time while the capture ran: 3 s, and whatever a loaded host adds before stop()
    # ends it (a test thread descheduled for 7 wall ms lets 70 clock ms more run); at clock rate 1 it would be 30,
    # and a loaded host drops some
    assert 150 <= mocap.frames <= 100 * (stopped - begun) + 1, (mocap.frames, stopped - begun)
    # Frames are stamped in clock time: the last one is near the clock's time at stop (a loaded host may start
    # the thread late, so not at 3.0 exactly); stamped in wall seconds it would read about 0.3.
    assert stopped - 0.5 < mocap.latest()["a"].t <= stopped, (mocap.latest()["a"].t, stopped)


def test_a_frozen_system_keeps_sending_the_old_pose_and_the_poses_say_so() -> None:
    """Frames keep arriving while "a" is frozen: each repeats its position exactly, ``still`` counts them and
    ``moved_t`` stays at the last frame that moved; a noisy standing body never looks frozen."""
    clock = ScaledClock(5.0)
    mocap = SimMocap(Walker(clock), FrameTransform(), clock, rate=50.0, noise=0.002, latency=0.0)
    frames = collect(mocap)
    try:
        t0 = started(mocap, clock)
        mocap.freeze("a", t0 + 0.5, t0 + 1.5)
        clock.sleep_until(t0 + 1.2)
        during = mocap.latest()["a"]
        clock.sleep_until(t0 + 2.0)
        after = mocap.latest()["a"]
    finally:
        mocap.stop()
    assert during.still >= 20 and during.t - during.moved_t > 0.5  # 50 Hz for 0.7 s: ~35 frames repeated
    assert np.allclose(during.pos[0], t0 + 0.5, atol=0.05)  # where it was when the freeze began
    assert after.still == 0 and after.moved_t == after.t
    assert max(f["b"].still for f in frames if "b" in f) == 0  # noise moves a standing body every frame
