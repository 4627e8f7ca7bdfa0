"""The deploy document (configs/deploy/*.json): what to fly, on what, and how safely.

Validated like the task documents: any problem raises
:class:`~atdrone.config.ConfigError` whose message starts with the JSON path, e.g.
``drones[2].role: must be one of ['learner', 'partner', 'evader'], got "pilot"``.

Keys (every one documented on its dataclass below):

- ``task``: a paper task name or task file (arena, obstacles, spawn regions, speeds).
- ``member``: the policy flown in the learner slots: ``{"checkpoint": PATH}``,
  ``{"registry": DB, "id": MEMBER}`` or ``{"model": "models:/atdrone-NAME@champion"}``.
- ``partners``: ``{"zoo": "zoo1"}`` (each episode draws the partner drones' members
  from the zoo) or ``{"members": ["greedy", "vicsek"]}`` (partner drone i flies member i,
  a rule or a checkpoint path).
- ``evaders``: ``"virtual"`` (simulated evaders the pursuers see, shown in the log) or
  ``"drones"`` (real drones flying the task's escape policy).
- ``drones``: name, radio URI, rigid-body name and role of every drone.
- ``backups``: drones waiting on the floor to take a partner slot whose drone was dropped
  (its battery ran low or its link was lost): name, radio URI, rigid body and the partner
  drones it may replace (``replaces``; every partner drone when empty).
- ``flight_height``, ``backend`` (``sim`` or ``cflib``), ``mocap``, ``frame``,
  ``frame_reference`` (a marker the preflight checks the frame with), ``radio``, ``shield``,
  ``sim`` (the simulated fleet and mocap), ``faults`` (injected on the sim backend),
  ``episodes``, ``horizon``, ``seed``, ``out_dir``.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal, NamedTuple, get_args

from atdrone.config import ConfigError, TaskConfig, _check, _non_negative, _positive, check_task_field, load_config
from atdrone.deploy.mocap import FrameTransform
from atdrone.deploy.shield import ShieldConfig

Role = Literal["learner", "partner", "evader"]
ROLES: tuple[str, ...] = get_args(Role)
FaultKind = Literal[
    "mocap_dropout",
    "mocap_freeze",
    "link_loss",
    "link_dropout",
    "pose_blocked",
    "drift",
    "low_battery",
    "policy_stall",
    "loop_hang",
    "host_pause",
    "exception",
    "signal",
]
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


@dataclass(frozen=True)
class MemberRef:
    """The member flown: exactly one of ``checkpoint``, ``registry`` + ``id``, or ``model``."""

    checkpoint: str = field(default="", metadata={"empty_ok": True})
    registry: str = field(default="", metadata={"empty_ok": True})
    id: str = field(default="", metadata={"empty_ok": True})
    model: str = field(default="", metadata={"empty_ok": True})


@dataclass(frozen=True)
class Partners:
    """Who flies the partner drones: a zoo (drawn per episode) or one member per partner drone."""

    zoo: str = field(default="", metadata={"empty_ok": True})
    members: tuple[str, ...] = ()


@dataclass(frozen=True)
class Drone:
    """One drone: its name, radio URI (cflib backend; the sim backend assigns its own), rigid body and role."""

    name: str
    role: Role
    uri: str = field(default="", metadata={"empty_ok": True})
    body: str = field(default="", metadata={"empty_ok": True})  # the motion-capture rigid body (default: name)

    @property
    def rigid_body(self) -> str:
        return self.body or self.name


@dataclass(frozen=True)
class Backup:
    """A backup drone: on the floor until a partner slot is dropped, then it takes off and takes that slot.

    name, uri (cflib backend) and body (the rigid body; default: name) as for a drone; replaces: the partner
    drones whose slot it may take (empty: any partner's). Backups are used in the order listed.
    """

    name: str
    uri: str = field(default="", metadata={"empty_ok": True})
    body: str = field(default="", metadata={"empty_ok": True})
    replaces: tuple[str, ...] = ()

    @property
    def rigid_body(self) -> str:
        return self.body or self.name


class Aboard(NamedTuple):
    """One physical drone of the flight, a backup's role ``backup``: what the backends and the loop need."""

    name: str
    role: str
    uri: str
    rigid_body: str


@dataclass(frozen=True)
class Mocap:
    """The motion-capture source of the cflib backend (the ``motioncapture`` package).

    ``type``: vicon, optitrack, qualisys, vrpn, mock, ...; ``hostname``; ``options``: more
    string settings passed through; ``connect_timeout`` seconds.
    """

    type: str = "mock"
    hostname: str = field(default="", metadata={"empty_ok": True})
    options: dict[str, str] = field(default_factory=dict)
    connect_timeout: float = field(default=5.0, metadata=_check(_positive))


@dataclass(frozen=True)
class SimSettings:
    """The simulated fleet and motion capture (sim backend).

    clock_rate: simulated seconds per wall second (1: real time); mocap_rate Hz;
    mocap_noise m (std); mocap_latency s; mocap_dropout: probability a body is missing
    from a frame; lag s: the attitude loop's lag behind the position controller; battery_drain
    V/s while the motors spin (0.002: 4.1 V to 3.4 V in about 6 minutes, like a Crazyflie's);
    true_frame: how the simulated mocap system is really mounted (default: as ``frame`` says);
    yaw_deg: the drones' true yaw as placed on the floor (90: facing +y, as they should);
    radio_model: the drones are reached through the Crazyradio model (one shared dongle, a
    one-packet queue, ~1000 packets/s) rather than straight over UDP; radio_loss: the probability
    a radio try is lost, radio_retries: the tries more a lost one gets (the radio's automatic retries).
    """

    clock_rate: float = field(default=1.0, metadata=_check(_positive))
    mocap_rate: float = field(default=100.0, metadata=_check(_positive))
    mocap_noise: float = field(default=0.002, metadata=_check(_non_negative))
    mocap_latency: float = field(default=0.01, metadata=_check(_non_negative))
    mocap_dropout: float = field(default=0.0, metadata=_check(lambda v: None if 0 <= v < 1 else "must be in [0, 1)"))
    lag: float = field(default=0.05, metadata=_check(_positive))
    yaw_deg: float = 90.0
    radio_model: bool = True
    radio_loss: float = field(default=0.05, metadata=_check(lambda v: None if 0 <= v < 1 else "must be in [0, 1)"))
    radio_retries: int = field(default=3, metadata=_check(_non_negative))
    battery_drain: float = field(default=0.002, metadata=_check(_non_negative))
    true_frame: FrameTransform | None = None


@dataclass(frozen=True)
class Fault:
    """A fault injected on the sim backend at clock time ``at`` (seconds since the loop started).

    With ``step`` (>= 0) it fires at that step of episode ``episode`` (from 0) instead, once ``at`` has passed
    (or on the first tick after that episode when it ended sooner): a time depends on the host's pace (how long
    the takeoff and the flights to the spawn took), a step does not.

    kind: mocap_dropout (``drone`` or the whole system when empty, for ``duration`` s),
    mocap_freeze (frames keep arriving with ``drone``'s pose, or every body's when empty,
    as it was, for ``duration`` s), link_loss (``drone``, for good), link_dropout
    (``drone``'s link carries nothing either way for ``duration`` s), pose_blocked (no
    motion-capture pose reaches ``drone``'s estimator for ``duration`` s, every other packet
    does: it dead-reckons and drifts), drift (``drone``
    pushed by ``accel`` m/s^2), low_battery (``drone`` at ``volts``), policy_stall (the
    policy takes ``duration`` s), loop_hang (the loop thread hangs ``duration`` s),
    host_pause (the whole ground-station process is stopped, SIGSTOP, for ``duration``
    wall seconds), exception (the loop raises), signal (the process gets ``signal``:
    SIGINT or SIGTERM).
    """

    kind: FaultKind
    at: float = field(metadata=_check(_non_negative))
    drone: str = field(default="", metadata={"empty_ok": True})
    duration: float = field(default=1.0, metadata=_check(_non_negative))
    accel: tuple[float, float, float] = (0.5, 0.0, 0.0)
    volts: float = field(default=3.2, metadata=_check(_positive))
    signal: Literal["SIGINT", "SIGTERM"] = "SIGINT"
    episode: int = field(default=0, metadata=_check(_non_negative))
    step: int = field(default=-1, metadata=_check(lambda v: None if v >= -1 else "must be >= 0 (or -1: at ``at``)"))


@dataclass(frozen=True)
class FrameReference:
    """A rigid body fixed in the arena at a known pose (a marker at the arena's corner): preflight checks that
    motion capture, through ``frame``, puts it there (within 0.1 m and 10 degrees)."""

    body: str
    pos: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw_deg: float = 0.0


@dataclass(frozen=True)
class Radio:
    """How the bridge talks to the drones.

    pose: ``extpose`` (position and quaternion: the estimator's yaw follows motion capture)
    or ``extpos`` (position only); pose_rate Hz the poses are sent at (30-50 for a few
    drones per radio); reset_estimator: set ``kalman.initialYaw`` and reset the estimator
    before flying; connect_timeout s; toc_cache: cflib's TOC cache directory ("": the
    user's cache directory); extpos_std m and extquat_std rad: the estimator's trust in
    motion capture; heartbeat_timeout s: the dead-man heartbeat feeds the firmware's
    emergency-stop watchdog only while the loop ticked this recently.
    """

    pose: Literal["extpose", "extpos"] = "extpose"
    pose_rate: float = field(default=50.0, metadata=_check(lambda v: None if 1 <= v <= 200 else "must be in [1, 200]"))
    reset_estimator: bool = True
    connect_timeout: float = field(default=10.0, metadata=_check(_positive))
    toc_cache: str = field(default="", metadata={"empty_ok": True})
    extpos_std: float = field(default=0.01, metadata=_check(_positive))
    extquat_std: float = field(default=0.01, metadata=_check(_positive))
    heartbeat_timeout: float = field(default=0.3, metadata=_check(_positive))


@dataclass(frozen=True)
class DeployConfig:
    """A deploy document (see the module docstring)."""

    task: str
    member: MemberRef
    drones: tuple[Drone, ...]
    backups: tuple[Backup, ...] = ()
    partners: Partners = field(default_factory=Partners)
    evaders: Literal["virtual", "drones"] = "virtual"
    name: str = "deploy"
    backend: Literal["sim", "cflib"] = "sim"
    flight_height: float = field(default=0.5, metadata=_check(_positive))
    takeoff_duration: float = field(default=2.0, metadata=_check(_positive))
    goto_speed: float = field(default=0.3, metadata=_check(_positive))  # m/s flying back to spawn between episodes
    mocap: Mocap = field(default_factory=Mocap)
    frame: FrameTransform = field(default_factory=FrameTransform)
    frame_reference: FrameReference | None = None
    radio: Radio = field(default_factory=Radio)
    shield: ShieldConfig = field(default_factory=ShieldConfig)
    sim: SimSettings = field(default_factory=SimSettings)
    faults: tuple[Fault, ...] = ()
    episodes: int = field(default=1, metadata=_check(_positive))
    horizon: int = field(default=0, metadata=_check(_non_negative))  # steps per episode; 0: the task's horizon
    min_battery_preflight: float = field(default=3.8, metadata=_check(_positive))
    spawn_tolerance: float = field(default=0.15, metadata=_check(_non_negative))
    seed: int = 0
    out_dir: str = "reports/deploy"

    def with_overrides(self, **changes: Any) -> DeployConfig:
        """A copy with the non-None ``changes`` applied and validated again."""
        cfg = replace(self, **{k: v for k, v in changes.items() if v is not None})
        validate(cfg)
        return cfg

    def role_names(self, role: str) -> list[str]:
        """The drones of a role, in document order."""
        return [d.name for d in self.drones if d.role == role]

    def fleet(self) -> list[Aboard]:
        """Every physical drone: the drones in document order, then the backups."""
        out = [Aboard(d.name, d.role, d.uri, d.rigid_body) for d in self.drones]
        return out + [Aboard(b.name, "backup", b.uri, b.rigid_body) for b in self.backups]


def task_of(cfg: DeployConfig) -> TaskConfig:
    return check_task_field(cfg.task)


def validate(cfg: DeployConfig) -> None:
    """Checks across fields: the member reference, roles against the task, faults against drones."""
    refs = [k for k in ("checkpoint", "model") if getattr(cfg.member, k)]
    if cfg.member.registry or cfg.member.id:
        if not (cfg.member.registry and cfg.member.id):
            raise ConfigError("member", "a registry member needs both 'registry' and 'id'")
        refs.append("registry")
    if len(refs) != 1:
        raise ConfigError("member", f"give exactly one of checkpoint, registry + id, model; got {refs or 'none'}")
    if cfg.member.model and not cfg.member.model.startswith("models:/"):
        raise ConfigError("member.model", f"must look like 'models:/NAME@ALIAS', got {cfg.member.model!r}")
    task = task_of(cfg)
    names = [d.name for d in cfg.drones]
    for i, d in enumerate(cfg.drones):
        if names.index(d.name) != i:
            raise ConfigError(f"drones[{i}].name", f"duplicate drone name {d.name!r}")
        if cfg.backend == "cflib" and not d.uri:
            raise ConfigError(f"drones[{i}].uri", "the cflib backend needs every drone's radio URI")
    counts = {r: len(cfg.role_names(r)) for r in ROLES}
    num_p, num_ctrl = task.players.num_p, task.players.num_ctrl
    if counts["learner"] != num_ctrl:
        raise ConfigError("drones", f"task {task.name} has {num_ctrl} learner slots, got {counts['learner']} learners")
    if counts["partner"] != num_p - num_ctrl:
        raise ConfigError(
            "drones", f"task {task.name} has {num_p - num_ctrl} partner slots, got {counts['partner']} partners"
        )
    want_e = task.players.num_e if cfg.evaders == "drones" else 0
    if counts["evader"] != want_e:
        raise ConfigError("drones", f"evaders {cfg.evaders!r} needs {want_e} evader drones, got {counts['evader']}")
    if bool(cfg.partners.zoo) == bool(cfg.partners.members):
        raise ConfigError("partners", "give exactly one of 'zoo' or 'members'")
    if cfg.partners.members and len(cfg.partners.members) != counts["partner"]:
        raise ConfigError(
            "partners.members",
            f"one member per partner drone: {counts['partner']} drones, got {len(cfg.partners.members)}",
        )
    _validate_backups(cfg)
    names += [b.name for b in cfg.backups]
    for i, f in enumerate(cfg.faults):
        if f.drone and f.drone not in names:
            raise ConfigError(f"faults[{i}].drone", f"no drone {f.drone!r} (drones: {', '.join(names)})")
        if f.kind in ("link_loss", "link_dropout", "pose_blocked", "drift", "low_battery") and not f.drone:
            raise ConfigError(f"faults[{i}].drone", f"a {f.kind} fault names its drone")
        if f.step >= 0 and f.episode >= cfg.episodes:
            raise ConfigError(f"faults[{i}].episode", f"the flight has {cfg.episodes} episode(s), from 0")
    lo, hi = cfg.shield.z_limits
    if not lo <= cfg.flight_height <= hi:
        raise ConfigError("flight_height", f"must lie within shield.z_limits {[lo, hi]}, got {cfg.flight_height}")
    if not NAME.match(cfg.name):
        raise ConfigError(
            "name", f"must be 1-64 letters, digits, '_', '.', '-' (not starting with those), got {cfg.name!r}"
        )
    if cfg.frame_reference is not None and cfg.frame_reference.body in {d.rigid_body for d in cfg.fleet()}:
        raise ConfigError("frame_reference.body", f"{cfg.frame_reference.body!r} is a drone's rigid body")


def _validate_backups(cfg: DeployConfig) -> None:
    """Each backup: a drone of no other role, a radio URI on the cflib backend, a rigid body of its own, and
    only partner drones to replace."""
    roles: dict[str, str] = {d.name: d.role for d in cfg.drones}
    partners = cfg.role_names("partner")
    bodies = {d.rigid_body: d.name for d in cfg.drones}
    if cfg.backups and not partners:
        raise ConfigError("backups", f"task {task_of(cfg).name} has no partner slots for a backup to take")
    for i, b in enumerate(cfg.backups):
        if not NAME.match(b.name):
            raise ConfigError(f"backups[{i}].name", f"must be 1-64 letters, digits, '_', '.', '-', got {b.name!r}")
        if roles.get(b.name) == "backup":
            raise ConfigError(f"backups[{i}].name", f"duplicate backup name {b.name!r}")
        if b.name in roles:
            why = f"{b.name!r} is already a {roles[b.name]} drone: a backup has no other role"
            raise ConfigError(f"backups[{i}].name", why)
        if cfg.backend == "cflib" and not b.uri:
            raise ConfigError(f"backups[{i}].uri", "the cflib backend needs every backup's radio URI")
        if b.rigid_body in bodies:
            raise ConfigError(f"backups[{i}].body", f"rigid body {b.rigid_body!r} is already {bodies[b.rigid_body]}'s")
        roles[b.name], bodies[b.rigid_body] = "backup", b.name
        for name in b.replaces:
            if name not in partners:
                raise ConfigError(
                    f"backups[{i}].replaces", f"no partner drone {name!r} (partner drones: {', '.join(partners)})"
                )


def load_deploy(path_or_doc: str | Path | Mapping[str, Any], **overrides: Any) -> DeployConfig:
    """A deploy document from configs/deploy/<name>.json, a path or a mapping, validated."""
    text = str(path_or_doc) if not isinstance(path_or_doc, Mapping) else ""
    if (
        text
        and not Path(text).is_file()
        and (Path(__file__).parents[2] / "configs" / "deploy" / f"{text}.json").is_file()
    ):
        path_or_doc = Path(__file__).parents[2] / "configs" / "deploy" / f"{text}.json"
    cfg: DeployConfig = load_config(DeployConfig, path_or_doc, "deploy", **overrides)
    validate(cfg)
    return cfg
