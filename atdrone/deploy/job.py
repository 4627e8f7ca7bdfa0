"""The deploy job: build the backend, run the dry run's checks, fly (only with ``arm``), log, report.

:func:`run_deploy` is what ``atdrone deploy CONFIG`` and ``jobs/deploy.py`` call:

1. the backend: ``sim`` (a :class:`~atdrone.deploy.simfleet.SimFleet` in its own process
   (:class:`~atdrone.deploy.simproc.FleetProcess`) on loopback UDP
   ports, :class:`~atdrone.deploy.mocap.SimMocap`, a scaled clock, the config's faults)
   or ``cflib`` (the configured radio URIs and a ``motioncapture`` source); both talk
   through the same :class:`~atdrone.deploy.bridge.CflibBridge`;
2. connect, stream motion-capture poses to the drones (extpos, at the mocap rate), run
   the preflight checks (:mod:`atdrone.deploy.preflight`) and print the plan;
3. without ``arm`` stop there (a dry run: nothing is ever armed); with it, fly
   (:class:`~atdrone.deploy.loop.Flight`) and write the flight log, log it to MLflow;
4. on the sim backend, ``compare`` puts the flown SUC/COL/AST beside the training
   simulator's evaluation of the same team on the same task (the gap to simulation).
"""

from __future__ import annotations

import dataclasses
import gc
import json
import math
import os
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.deploy.backup import backup_ground
from atdrone.deploy.bridge import Bridge, CflibBridge
from atdrone.deploy.clock import Clock, RealClock, ScaledClock
from atdrone.deploy.config import DeployConfig, task_of
from atdrone.deploy.flightlog import FlightLog, log_to_mlflow, summarize
from atdrone.deploy.gap import format_gap, simulation_gap
from atdrone.deploy.loop import FaultClock, Flight, StopRequest, Team
from atdrone.deploy.mocap import MocapSource, MotionCaptureSource, SimMocap
from atdrone.deploy.preflight import Preflight, plan_text, run_preflight
from atdrone.errors import STOP_SIGNALS, UserError
from atdrone.policies.base import Policy

__all__ = ["DeployError", "DeployResult", "format_gap", "run_deploy", "simulation_gap"]

Say = Callable[[str], None]


class DeployError(UserError, RuntimeError):
    """The deploy job cannot go on: a failed preflight, a member that cannot be had."""


@dataclass
class DeployResult:
    """What a deploy job did: its checks, whether it flew, its log directory and summary; ``ended_early`` the
    one-line reason an armed flight ended before its episodes were flown ("" when it did not)."""

    preflight: Preflight
    flown: bool
    log_dir: Path | None = None
    summary: dict[str, Any] | None = None
    run_id: str = ""
    gap: dict[str, Any] | None = None
    sent: dict[str, int] | None = None
    ended_early: str = ""
    episodes_flown: int = 0
    fleet: dict[str, dict[str, Any]] | None = None  # sim backend: per drone what the simulated firmware saw
    endings: dict[str, str] | None = None  # per drone: landed, cut in the air at Z m (STATE), lost (...)
    t0: float = 0.0  # clock time the flight started (the faults' time origin)
    stopped_by: str = ""  # the stop signal received (SIGTERM, SIGINT): every drone landed first; "" when none


def effective_task(cfg: DeployConfig) -> TaskConfig:
    """The task flown: the config's task with its horizon when the config sets one."""
    task = task_of(cfg)
    if cfg.horizon:
        task = dataclasses.replace(task, task=dataclasses.replace(task.task, task_horizon=cfg.horizon))
    return task


# ------------------------------------------------------------------ policies
def member_checkpoint(cfg: DeployConfig) -> Path:
    """The checkpoint file of the member flown (a path, a registry member, or an MLflow model)."""
    ref = cfg.member
    if ref.checkpoint:
        return Path(ref.checkpoint)
    if ref.registry:
        from atdrone.registry import Registry

        if not Path(ref.registry).is_file():
            raise DeployError(f"member.registry: no registry file {ref.registry!r}")
        with Registry(ref.registry, create=False) as reg:
            try:
                member = reg.member(ref.id)
            except KeyError as exc:
                raise DeployError(f"member.id: {exc.args[0]}") from None
        if not member.get("checkpoint"):
            raise DeployError(f"member.id: member {ref.id!r} has no checkpoint")
        path = Path(member["checkpoint"])
        path = path if path.is_absolute() else Path(ref.registry).parent / path
        from atdrone.models.checkpoint import CheckpointError, read_header

        try:
            digest = read_header(path)["sha256"]
        except CheckpointError as exc:
            raise DeployError(f"member.id: member {ref.id!r}: {exc}") from None
        if member.get("sha256") and digest != member["sha256"]:
            raise DeployError(
                f"member.id: member {ref.id!r}: checkpoint {path} has sha256 {digest[:12]}..., "
                f"the registry recorded {str(member['sha256'])[:12]}...: not the member registered"
            )
        return path
    from atdrone.tracking import model_checkpoint

    try:
        return Path(model_checkpoint(ref.model))
    except KeyError as exc:
        raise DeployError(f"member.model: {exc.args[0]}") from None


def build_team(cfg: DeployConfig) -> tuple[Team, str]:
    """The learner and partner policies of the flight; the learner's name."""
    from atdrone.policies.zoo import load_checkpoint, load_zoo, policy_from_spec

    path = member_checkpoint(cfg)
    import torch

    torch.set_num_threads(1)  # one small network per tick: extra threads only add latency beside cflib's threads
    learner = load_checkpoint(path)
    name = cfg.member.id or path.stem
    if cfg.partners.members:
        return Team(learner, [policy_from_spec(m) for m in cfg.partners.members]), name
    zoo = load_zoo(cfg.partners.zoo, task_of(cfg))
    if zoo.missing:
        raise DeployError(f"partners.zoo: zoo {zoo.name} is missing {', '.join(zoo.missing)}")
    pool = zoo.policies()
    slots = len(cfg.role_names("partner"))

    def draw(rng: np.random.Generator) -> list[Policy]:
        return [pool[i] for i in rng.integers(len(pool), size=slots)]

    return Team(learner, [pool[0]] * slots, draw_partners=draw), name


# ------------------------------------------------------------------ backends
@dataclass
class Backend:
    """A connected bridge, a running mocap source, their clock, the faults to inject (and the sim fleet)."""

    bridge: Bridge
    mocap: MocapSource
    clock: Clock
    faults: FaultClock
    fleet: Any = None


def ground_positions(cfg: DeployConfig, task: TaskConfig, seed: int) -> np.ndarray:
    """Where the simulated drones stand before takeoff: a spawn draw of the task whose drones are clear of each
    other's separation ellipsoids (z = 0); the backups along the fence (:func:`backup_ground`)."""
    from atdrone.deploy.transit import separated_spawn
    from atdrone.envs.rules import spawn

    rng = np.random.default_rng(seed)
    pursuers = cfg.role_names("learner") + cfg.role_names("partner")
    evaders = cfg.role_names("evader")

    def draw() -> tuple[np.ndarray, np.ndarray]:
        pos, _ = spawn(task, rng, 1)
        return pos[0, : len(pursuers)], pos[0, len(pursuers) : len(pursuers) + len(evaders)]

    pos_p, pos_e = separated_spawn(draw, cfg.shield.drone_radius, cfg.shield.drone_half_height)
    xy = {n: pos_p[i] for i, n in enumerate(pursuers)}
    xy.update({n: pos_e[j] for j, n in enumerate(evaders)})
    xy.update(zip([b.name for b in cfg.backups], backup_ground(task, cfg.shield, len(cfg.backups)), strict=True))
    return np.array([[*xy[d.name], 0.0] for d in cfg.fleet()])


def _bridge(cfg: DeployConfig, uris: dict[str, str], clock: Clock) -> CflibBridge:
    r = cfg.radio
    return CflibBridge(
        uris,
        clock,
        yaw=math.pi / 2,  # every drone faces +y, as every episode starts in training, and keeps that yaw
        extpos_std=r.extpos_std,
        extquat_std=r.extquat_std,
        connect_timeout=r.connect_timeout,
        cache_dir=r.toc_cache or None,
        pose_rate=r.pose_rate,
        heartbeat_timeout=r.heartbeat_timeout,
    )


@contextmanager
def collector_paused() -> Iterator[None]:
    """One full collection, then the heap frozen out of the collector's view and no collection until the block ends.

    A full collection holds the interpreter: every thread of the ground station stands still, 0.3-0.6 s in a
    process that has loaded torch, pandas and MLflow (measured on a loaded 2-core host), longer as its heap grows.
    Made while links are open, a stall past 2 s fails a send waiting on the radio (cflib's radio driver waits 2 s
    for its one-packet queue) and cflib drops that link; in flight, one also stops the heartbeat and the loop. So
    it is made here, before the backend connects, and none follows until every drone is down."""
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        gc.enable()


@contextmanager
def open_backend(cfg: DeployConfig, task: TaskConfig) -> Iterator[Backend]:
    """The configured backend, connected, poses flowing, estimators reset; everything closed on exit."""
    bodies = {d.rigid_body: d.name for d in cfg.fleet()}
    faults = FaultClock()
    fleet = None
    with ExitStack() as stack:
        mocap: MocapSource
        if cfg.backend == "sim":
            from atdrone.deploy.simdrone import DroneDynamics
            from atdrone.deploy.simproc import FleetProcess

            scaled = ScaledClock(cfg.sim.clock_rate)
            clock: Clock = scaled
            fleet = stack.enter_context(
                FleetProcess(
                    [d.name for d in cfg.fleet()],
                    ground_positions(cfg, task, cfg.seed + 7919),
                    scaled,
                    DroneDynamics(lag=cfg.sim.lag, battery_drain=cfg.sim.battery_drain),
                    yaw=math.radians(cfg.sim.yaw_deg),
                    radio=cfg.sim.radio_model,
                    radio_loss=cfg.sim.radio_loss,
                    radio_retries=cfg.sim.radio_retries,
                    seed=cfg.seed,
                )
            )
            truth = fleet.truth
            reference = cfg.frame_reference

            def bodies_truth() -> dict[str, tuple[np.ndarray, float]]:
                t = truth()
                seen = {b: t[n] for b, n in bodies.items()}
                if reference is not None:  # the marker really is where the config says
                    seen[reference.body] = (np.array(reference.pos, dtype=float), math.radians(reference.yaw_deg))
                return seen

            mocap = SimMocap(
                bodies_truth,
                cfg.frame,
                clock,
                rate=cfg.sim.mocap_rate,
                noise=cfg.sim.mocap_noise,
                latency=cfg.sim.mocap_latency,
                dropout=cfg.sim.mocap_dropout,
                seed=cfg.seed,
                true_transform=cfg.sim.true_frame or cfg.frame,
            )
            bridge = _bridge(cfg, fleet.uris, clock)
            _schedule(cfg, faults, fleet, mocap, clock)
        else:
            clock = RealClock()
            wanted = [d.rigid_body for d in cfg.fleet()] + ([cfg.frame_reference.body] if cfg.frame_reference else [])
            mocap = MotionCaptureSource(
                cfg.mocap.type,
                {"hostname": cfg.mocap.hostname, **cfg.mocap.options}
                if cfg.mocap.hostname
                else dict(cfg.mocap.options),
                wanted,
                cfg.frame,
                clock,
                connect_timeout=cfg.mocap.connect_timeout,
            )
            bridge = _bridge(cfg, {d.name: d.uri for d in cfg.fleet()}, clock)
        mocap.start()
        stack.callback(mocap.stop)
        bridge.open()
        stack.callback(bridge.close)
        with_quat = cfg.radio.pose == "extpose"
        mocap.on_frame(  # posting only fills the bridge's mailbox: the mocap thread never waits on the radio
            lambda poses: bridge.post_poses(
                {bodies[b]: (p.pos, p.quat if with_quat else None) for b, p in poses.items() if b in bodies}
            )
        )
        if cfg.radio.reset_estimator:
            clock.sleep(0.3)  # a few poses reach the drones first
            bridge.reset_estimators()
        yield Backend(bridge, mocap, clock, faults, fleet)


def _schedule(cfg: DeployConfig, faults: FaultClock, fleet: Any, mocap: SimMocap, clock: Clock) -> None:
    """Turn the config's faults into callables fired by the loop at their flight time."""
    body = {d.name: d.rigid_body for d in cfg.fleet()}
    for f in cfg.faults:
        fire: Callable[[], None]
        if f.kind == "mocap_dropout":
            fire = partial(_drop, mocap, clock, body[f.drone] if f.drone else None, f.duration)
        elif f.kind == "mocap_freeze":
            fire = partial(_freeze, mocap, clock, body[f.drone] if f.drone else None, f.duration)
        elif f.kind == "link_loss":
            fire = partial(fleet.cut_link, f.drone)
        elif f.kind == "link_dropout":
            fire = partial(fleet.cut_link, f.drone, f.duration)
        elif f.kind == "pose_blocked":
            fire = partial(fleet.block_poses, f.drone, f.duration)
        elif f.kind == "drift":
            fire = partial(fleet.push, f.drone, np.array(f.accel))
        elif f.kind == "low_battery":
            fire = partial(fleet.set_battery, f.drone, f.volts)
        elif f.kind == "policy_stall":
            fire = partial(setattr, faults, "stall", f.duration)
        elif f.kind == "loop_hang":
            fire = partial(setattr, faults, "hang", f.duration)
        elif f.kind == "host_pause":
            fire = partial(_pause_process, f.duration)
        elif f.kind == "signal":
            fire = partial(os.kill, os.getpid(), getattr(signal, f.signal))
        else:  # exception
            fire = partial(setattr, faults, "raise_now", True)
        faults.add(f.at, f.drone, f.kind, fire, f.episode, f.step)


def _drop(mocap: SimMocap, clock: Clock, body: str | None, duration: float) -> None:
    mocap.drop(body, clock.now(), clock.now() + duration)


def _freeze(mocap: SimMocap, clock: Clock, body: str | None, duration: float) -> None:
    mocap.freeze(body, clock.now(), clock.now() + duration)


def _pause_process(seconds: float) -> None:
    """Stop this whole process for ``seconds`` wall seconds (SIGSTOP, then SIGCONT from a helper process), as a
    host that deschedules the ground station would."""
    import subprocess
    import sys

    code = f"import os, signal, time; os.kill({os.getpid()}, signal.SIGSTOP); time.sleep({seconds}); "
    code += f"os.kill({os.getpid()}, signal.SIGCONT)"
    helper = subprocess.Popen([sys.executable, "-S", "-c", code])
    helper.wait()  # returns after the pause: this process was stopped meanwhile


# ------------------------------------------------------------------ the job
def run_deploy(
    cfg: DeployConfig,
    arm: bool = False,
    tracking_uri: str | None = None,
    compare: bool = False,
    say: Say = print,
    stop: StopRequest | None = None,
) -> DeployResult:
    """The deploy job (see the module docstring). Nothing arms unless ``arm``; a stop signal lands every drone
    and the result names it (:attr:`DeployResult.stopped_by`)."""
    stop = StopRequest() if stop is None else stop
    with stop.handling_signals():  # SIGINT / SIGTERM from here on: every drone lands
        result = _deploy(cfg, arm, tracking_uri, compare, say, stop)
    if stop.signal in {s.name for s in STOP_SIGNALS}:
        result.stopped_by = stop.signal
    return result


def _deploy(
    cfg: DeployConfig, arm: bool, tracking_uri: str | None, compare: bool, say: Say, stop: StopRequest
) -> DeployResult:
    task = effective_task(cfg)
    team, member = build_team(cfg)
    with collector_paused(), open_backend(cfg, task) as backend:
        log = FlightLog(
            {
                "name": cfg.name,
                "task": task.name,
                "member": member,
                "backend": cfg.backend,
                "evaders": cfg.evaders,
                "dt": task.dt,
                "arena": [task.site.boundary.width, task.site.boundary.height],
                "drones": {d.name: d.role for d in cfg.fleet()},
                "flight_height": cfg.flight_height,
                "clock_rate": backend.clock.rate,
            }
        )
        flight = Flight(
            cfg, task, team, backend.bridge, backend.mocap, backend.clock, log, backend.faults, stop, progress=say
        )
        say(f"[deploy] {cfg.name}: {cfg.backend} backend connected; preflight checks")
        pre = run_preflight(flight, cfg, task)
        say(pre.text())
        say(plan_text(cfg, member, task))
        if not pre.ok:
            say("[deploy] preflight failed: nothing armed")
            return DeployResult(pre, False, sent=dict(backend.bridge.sent()))
        if not arm:
            say("[deploy] dry run: nothing armed (pass --arm to fly)")
            return DeployResult(pre, False, sent=dict(backend.bridge.sent()))
        if stop:
            say(f"[deploy] stopped ({stop.signal}) before arming: nothing armed")
            return DeployResult(pre, False, sent=dict(backend.bridge.sent()))
        say(f"[deploy] arming and flying {cfg.episodes} episode(s)")
        started = time.perf_counter()
        log_dir = _log_dir(cfg)
        # nothing heavy runs while drones fly: writing the log (pandas, Parquet) holds the interpreter for 0.2-0.4 s,
        # past the dead-man limit of a scaled clock on a busy host; it is written once every drone is down
        flight.t0 = backend.clock.now()
        try:
            flight.run()  # lands every drone before it returns, whatever happened; never raises
        finally:
            log.overruns = flight.ticks.overruns
            log.meta.update(
                endings=flight.ended,
                ended_early=flight.aborted,
                episodes_flown=flight.episodes_flown,
                team_changes=flight.team_changes,
                mocap_callback_errors=getattr(backend.mocap, "callback_errors", 0),
            )
            log.write(log_dir)
        sent = dict(backend.bridge.sent())
        fleet = backend.fleet.report() if backend.fleet is not None else None
        if fleet is not None:  # what the simulated firmware saw, beside the log: true heights, impacts, cuts
            from atdrone.fileio import atomic_write_text

            atomic_write_text(log_dir / "fleet.json", json.dumps(fleet, indent=1))
        t0 = flight.t0
    summary = summarize(log_dir)
    run_id = log_to_mlflow(log_dir, tracking_uri, cfg.name)
    say(f"[deploy] flew in {time.perf_counter() - started:.0f} s wall; log {log_dir}; MLflow run {run_id}")
    result = DeployResult(
        pre, True, log_dir, summary, run_id, sent=sent, ended_early=flight.aborted, episodes_flown=flight.episodes_flown
    )
    result.fleet, result.t0, result.endings = fleet, t0, dict(flight.ended)
    say("[deploy] drones: " + ", ".join(f"{n} {e}" for n, e in flight.ended.items()))
    if flight.aborted:
        say(f"[deploy] flight ended early after {flight.episodes_flown}/{cfg.episodes} episode(s): {flight.aborted}")
    elif compare:
        result.gap = simulation_gap(cfg, task, team, summary)
    return result


def _log_dir(cfg: DeployConfig) -> Path:
    """A new directory name under out_dir for this flight (the name is checked: no path separators)."""
    base = Path(cfg.out_dir) / f"{cfg.name}-{time.strftime('%Y%m%d_%H%M%S')}"
    path, k = base, 1
    while path.exists():
        path, k = base.with_name(f"{base.name}-{k}"), k + 1
    return path
