"""One simulated Crazyflie's firmware and flight: estimator, controller, commander, supervisor, physics.

The behaviour follows facts read from crazyflie-firmware (the code is not copied):

- **Estimator** (Kalman-like, ``stabilizer.estimator`` = 2): position from ``extpos`` /
  ``extpose`` weighted by ``locSrv.extPosStdDev``; a yaw estimate that starts at
  ``kalman.initialYaw`` (0 by default) with a standard deviation of 0.01 rad and is
  corrected only by ``extpose`` (``locSrv.extQuatStdDev``); ``kalman.resetEstimation``
  restarts it (position variance 100^2 in x/y, so ``kalman.varPX`` settles only once
  extpos flows). Without positions for 0.2 s it dead-reckons: the IMU's velocity turned
  by the yaw error, plus an accelerometer bias (``imu_bias`` m/s^2, a fixed horizontal
  direction per drone) integrated since, so a blind drone drifts. The true attitude
  turns the commanded acceleration: a yaw estimate off by ``e`` turns every commanded
  acceleration by ``e``.
- **Controller** (Mellinger's position loop, ``ctrlMel.*``): commanded acceleration
  ``(kp (p_sp - p_est) + kd (v_sp - v_est)) / mass + a_sp`` with the firmware's default
  gains (kp_xy 0.4, kd_xy 0.2, kp_z 1.25, kd_z 0.4, mass 0.029 kg), realised through a
  first-order attitude lag and bounded by the thrust.
- **Commander**: every low-level setpoint stops the high-level planner (a high-level
  command that arrived while low-level setpoints streamed is dropped by the next one);
  ``notify_setpoint_stop`` hands over to the planner, which sends motors-off while it is
  idle. takeoff/land turn to the yaw they carry unless told to keep the current yaw. A
  legacy setpoint of zero thrust (cflib sends one when it closes a link) stops the
  motors in any mode.
- **Supervisor**: ``level_out`` s without a low-level setpoint the drone levels out;
  ``shutdown`` s the commander's watchdog stops the motors and locks the drone (a reboot
  is needed); once an emergency-stop watchdog packet arrived, another must follow within
  ``estop_watchdog`` s or the motors stop and the drone locks. The flying bit stays on
  until the motors idled ``flying_hysteresis`` s; ``landing_timeout`` s after that a
  drone (these need arming) is disarmed, so a takeoff needs arming again. Hitting the
  floor faster than ``tumble_impact`` leaves it tumbled (bit 5), and crashed and locked
  (bit 7) when its motors were on. Emergency stop locks; arming is needed before
  anything spins.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from atdrone.deploy import crtp
from atdrone.envs.kinematics import wrap_angle

GRAVITY = 9.81

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
    ("ctrlMel", "mass", "float", 0.029),
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
    imu_bias: float = 0.05  # m/s^2: the accelerometer bias dead reckoning integrates without motion capture
    flying_hysteresis: float = 2.0  # s of idle motors before the supervisor stops reporting the drone flying
    landing_timeout: float = 3.0  # s after landing a drone that needs arming is disarmed
    tumble_impact: float = 1.0  # m/s: hitting the ground faster than this leaves the drone tumbled


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
    link_back: float = np.inf  # clock time a cut link carries again
    bias_dir: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))  # the IMU bias' direction
    last_thrust: float = -np.inf  # clock time the motors last spun
    landed_at: float | None = None  # clock time the supervisor stopped reporting it flying (armed, unlocked)
    tumbled: bool = False
    crashed: bool = False
    impacts: list[tuple[float, float, bool]] = field(default_factory=list)  # (clock time, speed m/s, motors on)
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
        turned by the yaw error, with the accelerometer's bias integrated since (dead reckoning drifts)."""
        blind = self.now - self.last_measure - 0.2
        if blind <= 0:
            return self.vel.copy()
        drift = self.dyn.imu_bias * min(blind, 60.0) * self.bias_dir
        return _rotate(self.vel, -self.yaw_error) + drift

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
        if self.plan is not None:  # every low-level setpoint stops the planner: a queued command is dropped
            self.counts["hl_dropped" if self.mode == "ll" else "hl_stopped"] += 1
            self.plan = None
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
        """Motors off and locked until a reboot (the supervisor's locked state)."""
        self.counts[why] += 1
        self.history.append((now, why))
        self.motors_on, self.locked, self.armed, self.mode, self.plan = False, True, False, "idle", None

    def flying(self) -> bool:
        """The supervisor's flying bit: motors spun within the hysteresis, and not locked."""
        return not self.locked and self.now - self.last_thrust < self.dyn.flying_hysteresis

    def _supervise(self, now: float) -> None:
        """The supervisor's landing timeout: landed (not flying any more) for ``landing_timeout`` s -> disarmed."""
        if self.motors_on:
            self.last_thrust, self.landed_at = now, None
        elif self.landed_at is None and self.armed and np.isfinite(self.last_thrust) and not self.flying():
            self.landed_at = now
        if self.landed_at is not None and now - self.landed_at > self.dyn.landing_timeout and self.armed:
            self.armed = False
            self.counts["landing_timeout_disarm"] += 1
            self.landed_at = None

    def _ground(self, now: float) -> None:
        """Contact with the floor: an impact faster than ``tumble_impact`` leaves the drone tumbled (crashed, and
        locked, when its motors were on)."""
        if self.pos[2] > 0:
            return
        speed = -float(self.vel[2])
        if speed > 0.05:
            self.impacts.append((now, speed, self.motors_on))
        if speed > self.dyn.tumble_impact:
            self.tumbled = True
            if self.motors_on:
                self.crashed = True
                self.emergency_stop(now, "crashed")
        self.pos[2] = 0.0
        self.vel = np.zeros(3) if not self.motors_on else np.array([self.vel[0], self.vel[1], max(0.0, self.vel[2])])

    # ------------------------------------------------------------ physics
    def step(self, now: float, dt: float) -> None:
        d = self.dyn
        self.now = now
        if self.link_cut and now >= self.link_back:
            self.link_cut, self.link_back = False, np.inf
        if self.estop_wd is not None and now - self.estop_wd > d.estop_watchdog and not self.locked:
            self.emergency_stop(now, "estop_watchdog")
        self._supervise(now)
        if self.motors_on:
            self.battery -= d.battery_drain * dt
        # the estimator's prediction (IMU dead reckoning) between measurements
        self.est_pos = self.est_pos + self.est_vel() * dt
        self.var_pos = self.var_pos + PROCESS_NOISE_POS * dt
        self.var_yaw = self.var_yaw + PROCESS_NOISE_YAW * dt
        levelled = False
        if self.mode == "ll" and self.motors_on:
            age = now - self.last_setpoint
            if age > d.shutdown:  # the commander's watchdog: motors off and locked (a reboot is needed)
                self.emergency_stop(now, "watchdog_shutdown")
            elif age > d.level_out:
                levelled = True
        if not self.motors_on:
            self.acc = np.zeros(3)
            if self.pos[2] > 0:
                self.vel = np.array([0.0, 0.0, self.vel[2] - GRAVITY * dt])
                self.pos = self.pos + self.vel * dt
            if self.pos[2] <= 0:
                self._ground(now)
            return
        if self.mode == "hl" and self.plan is not None:
            target, target_vel, done = self.plan.at(now)
            if self.plan.yaw is not None:
                self.sp_yaw = self.plan.yaw
            # landed: the trajectory ended at the floor and the drone sits on it; the planner stops the motors
            if self.plan.landing and done and self.est_pos[2] < 0.05 and (self.pos[2] <= 0.005 or self._settled(now)):
                self.motors_on, self.mode, self.plan = False, "idle", None
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
            self._ground(now)
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

    def _settled(self, now: float) -> bool:
        """A second past the end of the landing trajectory (the estimate says down, the floor was not met)."""
        return self.plan is not None and now - self.plan.t0 - self.plan.duration > 1.0

    def supervisor_bits(self) -> int:
        finished = self.plan is not None and self.now >= self.plan.t0 + self.plan.duration
        return (
            int(not self.locked) << crtp.BIT_CAN_BE_ARMED
            | int(self.armed) << crtp.BIT_IS_ARMED
            | int(self.armed and not self.locked) << crtp.BIT_CAN_FLY
            | int(self.flying()) << crtp.BIT_IS_FLYING
            | int(self.tumbled) << crtp.BIT_TUMBLED
            | int(self.locked) << crtp.BIT_LOCKED
            | int(self.crashed) << crtp.BIT_CRASHED
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
