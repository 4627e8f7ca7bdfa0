"""Motion capture: rigid-body poses in the arena frame, read in their own thread or process.

Two sources share one interface (:class:`MocapSource`) and one path from mocap data to
poses (:meth:`FrameTransform.to_arena`), so a wrong ``frame`` in the deploy config shows
in simulation exactly as it would on hardware:

- :class:`MotionCaptureSource`: the real systems through the ``motioncapture`` package
  (vicon, optitrack, qualisys, vrpn, mock, ...). The package is driven in a child process:
  some of its backends (vicon, optitrack) block inside ``connect`` while holding the GIL,
  which would freeze every Python thread of the flight; a child process can be timed out
  and killed. Frames come back over a pipe and are timed on arrival (no timestamps reach
  Python from libmotioncapture).
- :class:`SimMocap`: a simulated system reading the simulated fleet's truth on the
  deploy clock, with noise, latency, random dropout and scheduled outages.

Conventions. Positions in metres. The arena frame has its origin at the arena's corner,
x along the width, y along the height, z up. Yaw is in radians, counter-clockwise from
the arena's +x axis seen from above, wrapped to [-pi, pi). Quaternions are (w, x, y, z).
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing
import re
import threading
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Protocol

import numpy as np

from atdrone.config import ConfigError, _check
from atdrone.deploy.clock import Clock
from atdrone.envs.kinematics import wrap_angle
from atdrone.errors import UserError

log = logging.getLogger(__name__)

_AXIS = re.compile(r"^([+-]?)([xyz])$")
STARTUP_TIMEOUT = 20.0  # wall seconds for the reader process to start (imports), before connect_timeout
NOISE_FLOOR = 1e-5  # m: a body whose position changes less than this between frames did not move (or froze)
FROZEN_FRAMES = 5  # frames in a row without a change above the noise floor: a frozen pose, while commanded to move


class MocapError(UserError, RuntimeError):
    """The motion-capture system cannot be reached or read."""


def _parse_axes(axes: Sequence[str]) -> tuple[np.ndarray | None, str | None]:
    """The 3x3 matrix mapping mocap to arena coordinates, or why ``axes`` is invalid."""
    if len(axes) != 3:
        return None, f"must name 3 axes, got {len(axes)}"
    matrix = np.zeros((3, 3))
    for i, spec in enumerate(axes):
        m = _AXIS.match(str(spec).strip())
        if m is None:
            return None, f"each axis is a signed mocap axis like 'x' or '-y', got {spec!r} at [{i}]"
        matrix[i, "xyz".index(m.group(2))] = -1.0 if m.group(1) == "-" else 1.0
    if not (np.abs(matrix).sum(0) == 1).all():
        return None, f"must use each of x, y, z exactly once (a signed permutation), got {list(axes)}"
    if np.linalg.det(matrix) < 0:
        flipped = [axes[0][1:] if axes[0].startswith("-") else f"-{axes[0].lstrip('+')}", *axes[1:]]
        return None, (
            f"{list(axes)} is a left-handed frame (a mirror image, not a rotation of the mocap frame): "
            f"flip the sign of one axis, e.g. {flipped}"
        )
    return matrix, None


def _axes_problem(axes: tuple[str, str, str]) -> str | None:
    return _parse_axes(axes)[1]


def _quat_of_matrix(m: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) of one rotation matrix (Shepperd's method)."""
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return np.array(q) / np.linalg.norm(q)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a * b of (..., 4) quaternions (w, x, y, z)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


@dataclass(frozen=True)
class FrameTransform:
    """The arena frame in the mocap frame: the ``frame`` section of the deploy config.

    origin: the arena's corner (0, 0, 0) in mocap coordinates (metres).
    axes: which signed mocap axis is the arena's x, y and z, e.g. ``["-y", "x", "z"]``
    (arena x = -mocap y, arena y = mocap x, arena z = mocap z) or ``["x", "-z", "y"]``
    for a Y-up system; a signed permutation making a right-handed frame.
    yaw_offset_deg: added to the yaw of each rigid body's x-axis after the axis mapping:
    ``arena yaw = yaw of the body's x-axis in the arena frame + yaw_offset_deg``. With the
    default axes this is ``arena yaw = mocap yaw + offset``; use it when the rigid bodies
    were defined with their x-axis off the drones' front (e.g. 90 when each body's x-axis
    points to the drone's right, so that its front is the body's +y).

    So ``p_arena = A (p_mocap - origin)`` with A the axes' matrix, and the yaw is
    ``atan2`` of the body x-axis ``A R(q) e_x`` projected on the arena's floor, plus the offset.
    """

    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axes: tuple[str, str, str] = field(default=("x", "y", "z"), metadata=_check(_axes_problem))
    yaw_offset_deg: float = 0.0

    def __post_init__(self) -> None:
        matrix, problem = _parse_axes(self.axes)
        if problem is not None:
            raise ConfigError("axes", problem)
        object.__setattr__(self, "_matrix", matrix)
        # the quaternion of the arena frame's orientation in the mocap frame (rotation A^T)
        object.__setattr__(self, "_q_arena", _quat_of_matrix(np.asarray(matrix).T))

    @property
    def matrix(self) -> np.ndarray:
        """A (3, 3): arena coordinates of a mocap vector are ``A @ v``."""
        m: np.ndarray = self._matrix  # type: ignore[attr-defined]
        return m

    def to_arena(self, pos: np.ndarray, quat_wxyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mocap positions (D, 3) and orientations (D, 4) -> arena positions (D, 3), yaws (D,)."""
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(quat_wxyz, dtype=np.float64).reshape(-1, 4)
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        w, x, y, z = q.T
        body_x = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)], -1)  # R(q) e_x
        heading = body_x @ self.matrix.T
        arena = (pos - np.asarray(self.origin)) @ self.matrix.T
        yaw = np.arctan2(heading[:, 1], heading[:, 0]) + math.radians(self.yaw_offset_deg)
        return arena, wrap_angle(yaw)

    def quat_to_arena(self, quat_wxyz: np.ndarray) -> np.ndarray:
        """Mocap orientations (D, 4) -> orientations (D, 4) (w, x, y, z) in the arena frame, the yaw offset
        included (their yaw is :meth:`to_arena`'s): what ``send_extpose`` tells the drone's estimator."""
        q = np.asarray(quat_wxyz, dtype=np.float64).reshape(-1, 4)
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
        conj = self._q_arena * np.array([1.0, -1.0, -1.0, -1.0])  # type: ignore[attr-defined]
        half = math.radians(self.yaw_offset_deg) / 2
        q_off = np.array([math.cos(half), 0.0, 0.0, math.sin(half)])
        return _quat_mul(q_off, _quat_mul(conj, q))

    def to_mocap(self, pos: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The inverse of :meth:`to_arena` for level bodies: arena (D, 3), yaws (D,) -> mocap (D, 3), (D, 4)."""
        pos = np.asarray(pos, dtype=np.float64).reshape(-1, 3)
        half = 0.5 * (np.asarray(yaw, dtype=np.float64).reshape(-1) - math.radians(self.yaw_offset_deg))
        q_yaw = np.stack([np.cos(half), np.zeros_like(half), np.zeros_like(half), np.sin(half)], -1)
        mocap = pos @ self.matrix + np.asarray(self.origin)
        return mocap, _quat_mul(self._q_arena, q_yaw)  # type: ignore[attr-defined]


@dataclass(frozen=True, eq=False)
class Pose:
    """A rigid body's pose in the arena frame; ``t`` is the clock time the frame ARRIVED; ``still`` counts the
    frames in a row before this one whose position it repeats within :data:`NOISE_FLOOR`, ``moved_t`` is the
    arrival time of the last frame that moved (a frozen system keeps sending the same pose)."""

    t: float
    pos: np.ndarray  # (3,)
    yaw: float  # radians, counter-clockwise from the arena's +x
    quat: np.ndarray | None = None  # (w, x, y, z) in the arena frame
    still: int = 0
    moved_t: float = math.nan


FrameCallback = Callable[[dict[str, Pose]], None]


class MocapSource(Protocol):
    """A running motion-capture system delivering arena-frame poses."""

    frames: int  # frames received

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def latest(self) -> dict[str, Pose]:
        """The newest pose of each rigid body seen so far (thread-safe)."""
        ...

    def on_frame(self, callback: FrameCallback) -> None:
        """Call ``callback(poses)`` from the reader thread with each frame's poses."""
        ...


class _Poses:
    """What both sources share: frame -> arena poses -> latest() and the callbacks."""

    def __init__(self, transform: FrameTransform, clock: Clock) -> None:
        self.transform, self.clock = transform, clock
        self.frames = 0
        self.callback_errors = 0
        self._latest: dict[str, Pose] = {}
        self._callbacks: list[FrameCallback] = []
        self._lock = threading.Lock()

    def latest(self) -> dict[str, Pose]:
        with self._lock:
            return dict(self._latest)

    def on_frame(self, callback: FrameCallback) -> None:
        with self._lock:
            self._callbacks.append(callback)

    def _publish(self, names: Sequence[str], pos: np.ndarray, quat: np.ndarray) -> None:
        """One frame of mocap-frame data arrived now: bodies with a non-finite position are unseen."""
        t = self.clock.now()
        seen = np.isfinite(pos).all(1) & np.isfinite(quat).all(1)
        arena, yaw = self.transform.to_arena(pos[seen], quat[seen])
        q_arena = self.transform.quat_to_arena(quat[seen])
        kept = [n for n, s in zip(names, seen, strict=True) if s]
        with self._lock:
            poses = {}
            for i, n in enumerate(kept):
                prev = self._latest.get(n)
                if prev is not None and float(np.abs(arena[i] - prev.pos).max()) <= NOISE_FLOOR:
                    poses[n] = Pose(t, arena[i], float(yaw[i]), q_arena[i], prev.still + 1, prev.moved_t)
                else:
                    poses[n] = Pose(t, arena[i], float(yaw[i]), q_arena[i], 0, t)
            self._latest.update(poses)
            self.frames += 1
            callbacks = list(self._callbacks)
        for callback in callbacks:
            try:
                callback(poses)
            except Exception:  # a failing consumer must not stop the poses; log it once
                self.callback_errors += 1
                if self.callback_errors == 1:
                    log.exception("motion-capture frame callback failed (further failures counted silently)")


# ------------------------------------------------------------------ the real systems
def _string_cfg(cfg: Mapping[str, Any]) -> dict[str, str]:
    """libmotioncapture takes every setting as a string (booleans as true/false)."""
    return {str(k): (str(v).lower() if isinstance(v, bool) else str(v)) for k, v in cfg.items()}


def _reader_main(kind: str, cfg: dict[str, str], bodies: list[str], conn: Connection) -> None:
    """The reader process: connect, then send each frame's wanted bodies as (names, (n, 7) array)."""
    try:
        try:
            import motioncapture
        except ImportError as exc:
            conn.send(("error", f"the motioncapture package is missing ({exc}): pip install 'atdrone[deploy]'"))
            return
        conn.send(("connecting", None))
        try:
            mc = motioncapture.connect(kind, cfg)
        except Exception as exc:
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
            return
        conn.send(("connected", None))
        wanted = set(bodies)
        while True:
            mc.waitForNextFrame()
            rigid = mc.rigidBodies
            names = [n for n in rigid if not wanted or n in wanted]
            data = np.array([[*rigid[n].position, *_wxyz(rigid[n].rotation)] for n in names], dtype=np.float64)
            conn.send(("frame", (names, data.reshape(-1, 7))))
    except (BrokenPipeError, EOFError, OSError):  # the parent went away or closed the pipe
        return
    except Exception as exc:  # a backend failing mid-stream
        with contextlib.suppress(OSError):
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


def _wxyz(rotation: Any) -> tuple[float, float, float, float]:
    """A motioncapture rotation (a Quaternion with w, x, y, z, or a sequence in that order)."""
    if hasattr(rotation, "w"):
        return float(rotation.w), float(rotation.x), float(rotation.y), float(rotation.z)
    w, x, y, z = (float(v) for v in rotation)
    return w, x, y, z


class MotionCaptureSource(_Poses):
    """A real motion-capture system through the ``motioncapture`` package.

    kind: vicon, optitrack, qualisys, vrpn, mock, ... (what the installed build offers);
    cfg: its settings, e.g. ``{"hostname": "192.168.1.10"}``, passed as strings; the mock
    backend takes ``rigid_bodies`` (``"cf1(x,y,z,qw,qx,qy,qz);cf2(...)"``, static poses)
    and ``frequency`` (Hz). bodies: the rigid bodies to report (empty: all).
    :meth:`start` raises :class:`MocapError` naming the kind and hostname when the
    system cannot be reached within ``connect_timeout`` seconds or the kind is unknown.
    """

    def __init__(
        self,
        kind: str,
        cfg: Mapping[str, str],
        bodies: Sequence[str],
        transform: FrameTransform,
        clock: Clock,
        connect_timeout: float = 5.0,
    ) -> None:
        super().__init__(transform, clock)
        self.kind = kind
        self.cfg = _string_cfg(cfg)
        self.bodies = list(bodies)
        self.connect_timeout = connect_timeout
        self.error = ""  # why reading stopped, when it failed mid-flight
        self._process: Any = None
        self._conn: Connection | None = None
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()

    @property
    def where(self) -> str:
        return f"{self.kind} motion capture at {self.cfg.get('hostname', 'localhost')}"

    def start(self) -> None:
        if self._thread is not None:
            return
        ctx = multiprocessing.get_context("spawn")  # no fork: the parent runs cflib's threads
        recv, send = ctx.Pipe(duplex=False)
        proc = ctx.Process(
            target=_reader_main, args=(self.kind, self.cfg, self.bodies, send), name=f"mocap-{self.kind}", daemon=True
        )
        proc.start()
        send.close()
        self._process, self._conn = proc, recv
        try:
            self._expect("connecting", STARTUP_TIMEOUT, "the reader process did not start")
            self._expect("connected", self.connect_timeout, f"no connection within {self.connect_timeout:g} s")
        except MocapError:
            self._kill()
            raise
        self._stopping.clear()
        self._thread = threading.Thread(target=self._read, name=f"mocap-{self.kind}", daemon=True)
        self._thread.start()

    def _expect(self, what: str, timeout: float, why: str) -> None:
        assert self._conn is not None
        try:
            ready = self._conn.poll(timeout)
            message = self._conn.recv() if ready else None
        except (EOFError, OSError):
            raise MocapError(f"{self.where}: the reader process died") from None
        if message is None:
            raise MocapError(f"{self.where}: {why}")
        kind, payload = message
        if kind == "error":
            if "Unknown motion capture type" in str(payload):
                raise MocapError(
                    f"unknown motion-capture type {self.kind!r}: the installed motioncapture build offers "
                    "vicon, optitrack, qualisys, vrpn, mock (others, e.g. fzmotion, need a source build)"
                )
            raise MocapError(f"{self.where}: {payload}")
        if kind != what:  # pragma: no cover - protocol bug
            raise MocapError(f"{self.where}: expected {what!r} from the reader process, got {kind!r}")

    def _read(self) -> None:
        conn = self._conn
        assert conn is not None
        while not self._stopping.is_set():
            try:
                kind, payload = conn.recv()
            except (EOFError, OSError):
                if not self._stopping.is_set():
                    self.error = "the reader process ended"
                    log.error("%s: %s; no more poses", self.where, self.error)
                return
            if kind == "frame":
                names, data = payload
                self._publish(names, data[:, :3], data[:, 3:])
            elif kind == "error":
                self.error = str(payload)
                log.error("%s: %s; no more poses", self.where, self.error)
                return

    def _kill(self) -> None:
        proc = self._process
        if proc is not None:
            proc.terminate()
            proc.join(2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        self._process = None

    def stop(self) -> None:
        self._stopping.set()
        self._kill()  # the pipe's far end closes: the reader thread sees EOF
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None


# ------------------------------------------------------------------ simulated motion capture
Truth = Callable[[], dict[str, tuple[np.ndarray, float]]]


class SimMocap(_Poses):
    """Simulated motion capture of the simulated fleet, on the deploy clock.

    Every ``1 / rate`` clock seconds: ``truth()`` (arena positions and yaws) -> mocap
    coordinates by ``true_transform`` (how the simulated system is really mounted;
    default: ``transform``) -> Gaussian position noise (``noise`` m std per axis) ->
    each body independently missing with probability ``dropout``, and bodies (or the
    whole system) silenced by :meth:`drop` -> delivered ``latency`` clock seconds later
    -> :meth:`FrameTransform.to_arena` by ``transform`` (what the config says), exactly
    as the real source does. A late thread does not burst: more than 5 periods behind,
    the schedule restarts from now.
    """

    def __init__(
        self,
        truth: Truth,
        transform: FrameTransform,
        clock: Clock,
        rate: float = 100.0,
        noise: float = 0.002,
        latency: float = 0.01,
        dropout: float = 0.0,
        seed: int = 0,
        true_transform: FrameTransform | None = None,
    ) -> None:
        super().__init__(transform, clock)
        if not rate > 0:
            raise ValueError(f"rate must be > 0, got {rate!r}")
        if noise < 0 or latency < 0 or not 0 <= dropout < 1:
            raise ValueError(f"need noise >= 0, latency >= 0, 0 <= dropout < 1; got {noise}, {latency}, {dropout}")
        self.truth, self.rate, self.noise, self.latency, self.dropout = truth, rate, noise, latency, dropout
        self.true_transform = true_transform or transform
        self.rng = np.random.default_rng(seed)
        self._drops: list[tuple[str | None, float, float]] = []
        self._freezes: list[tuple[str | None, float, float]] = []
        self._frozen: dict[tuple[str, float], tuple[np.ndarray, np.ndarray]] = {}  # (body, start) -> its frozen pose
        self.error = ""  # why the frames stopped, when the truth failed
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None

    def drop(self, body: str | None, start: float, end: float) -> None:
        """Send nothing of ``body`` (the whole system when None) for frames captured in [start, end) clock s."""
        with self._lock:
            self._drops.append((body, start, end))

    def freeze(self, body: str | None, start: float, end: float) -> None:
        """Keep sending the pose ``body`` (every body when None) had at ``start`` for frames captured in
        [start, end) clock s: a frozen system whose frames keep arriving."""
        with self._lock:
            self._freezes.append((body, start, end))

    def start(self) -> None:
        if self._thread is None:
            self._stopping.clear()
            self._thread = threading.Thread(target=self._run, name="sim-mocap", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stopping.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None

    def _capture(self, t: float) -> tuple[list[str], np.ndarray, np.ndarray] | None:
        """One frame captured at clock time ``t`` in mocap coordinates, or None when the system is silent."""
        with self._lock:
            silenced = {b for b, s, e in self._drops if s <= t < e}
        if None in silenced:
            return None
        truth = self.truth()
        names = [n for n in truth if n not in silenced]
        if self.dropout > 0:
            names = [n for n, keep in zip(names, self.rng.random(len(names)) >= self.dropout, strict=True) if keep]
        pos = np.array([truth[n][0] for n in names], dtype=np.float64).reshape(-1, 3)
        yaw = np.array([truth[n][1] for n in names], dtype=np.float64)
        mocap, quat = self.true_transform.to_mocap(pos, yaw)
        if self.noise > 0:
            mocap = mocap + self.rng.normal(0.0, self.noise, mocap.shape)
        with self._lock:
            freezes = [(b, s) for b, s, e in self._freezes if s <= t < e]
        for k, n in enumerate(names):
            start = next((s for b, s in freezes if b is None or b == n), None)
            if start is not None:
                kept = self._frozen.setdefault((n, start), (mocap[k].copy(), quat[k].copy()))
                mocap[k], quat[k] = kept
        return names, mocap, quat

    def _run(self) -> None:
        try:
            self._frames_loop()
        except Exception as exc:  # e.g. the fleet closed under us: poses go stale, the shield sees it
            self.error = f"{type(exc).__name__}: {exc}"
            log.exception("simulated motion capture stopped")

    def _frames_loop(self) -> None:
        clock, period = self.clock, 1.0 / self.rate
        pending: deque[tuple[float, list[str], np.ndarray, np.ndarray]] = deque()
        due = clock.now()
        while not self._stopping.is_set():
            now = clock.now()
            while pending and pending[0][0] <= now:
                _, names, pos, quat = pending.popleft()
                self._publish(names, pos, quat)
            if now >= due:
                frame = self._capture(now)
                if frame is not None:
                    pending.append((now + self.latency, *frame))
                due = now + period if now - due > 5 * period else due + period
                continue
            wake = min(due, pending[0][0]) if pending else due
            self._stopping.wait(max(0.0, wake - now) / clock.rate)
