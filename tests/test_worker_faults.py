"""Faults injected into the rollout workers: one killed mid-collect, a fresh one replaying a job, one dead past its
restarts, one that keeps dying. Each either returns what an uninterrupted worker returns or fails naming the worker."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np
import pytest
import ray

from atdrone.config import load_task
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import ppo_config
from atdrone.policies.zoo import MemberSpec
from atdrone.service.actors import RolloutJob, RolloutWorkerActor
from atdrone.teams.partners import Uniform

TASK = load_task("4p2e1o")


# ------------------------------------------------------------------ a rollout worker killed mid-collect
def _job() -> tuple[RolloutJob, list[Any]]:
    """A job against a greedy and a Vicsek drone (drawn per slot and episode) and 5 updates' distinct weights."""
    ppo = ppo_config(
        {"epochs": 2, "entity_dim": 8, "hidden": 16, "num_envs": 8, "rollout_steps": 192, "minibatch_size": 64}
    )
    zoo = (MemberSpec("greedy", "greedy"), MemberSpec("vicsek", "vicsek"))
    specs = [LearnerSpec(ppo=ppo, num_e=2, num_p=4, seed=s, total_updates=5) for s in range(5)]
    weights = [ray.put(Learner(spec).get_weights()) for spec in specs]
    arch = Learner(specs[0]).model.architecture()
    job = RolloutJob(1234, ppo, 4, TASK.players.num_ctrl, arch, zoo, Uniform(tuple(m.name for m in zoo)))
    return job, weights


def _collect(worker: Any, job: RolloutJob, weights: list[Any], u: int) -> Any:
    return worker.collect.remote(job, weights[u], job.ppo.rollout_steps, u, weights[:u])


def _same_fragment(a: Any, b: Any) -> None:
    for name in ("obs", "u", "logp", "values", "rewards", "dones", "last_values"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.episodes == b.episodes
    assert a.extras.keys() == b.extras.keys()
    for name in a.extras:
        np.testing.assert_array_equal(a.extras[name], b.extras[name], err_msg=name)


def test_a_worker_killed_mid_collect_returns_the_fragments_and_draws_of_an_uninterrupted_one(local_ray):
    """Worker B is killed while it collects fragment 2 (a pid probe queued behind the collect goes
    unanswered, and is later answered by the restarted process), and again idle before fragment 4. Ray
    restarts it and retries the call; the job replays from its start, so every fragment (arrays, finished
    episodes and their partners) and the partner draws equal those of worker A, never interrupted."""
    job, weights = _job()
    a, b = RolloutWorkerActor.remote(TASK), RolloutWorkerActor.remote(TASK)
    try:
        want = [ray.get(_collect(a, job, weights, u)) for u in range(5)]
        want_drawn = ray.get(a.drawn.remote(job, weights, job.ppo.rollout_steps))
        assert sum(want_drawn.values()) > job.num_envs  # episodes ended and new partners were drawn
        assert {p for profile in want_drawn for p in profile.split("|")} == {"greedy", "vicsek"}

        got = [ray.get(_collect(b, job, weights, u)) for u in range(2)]
        first_pid = ray.get(b.pid.remote())
        pending = _collect(b, job, weights, 2)
        deadline = time.monotonic() + 60
        while True:  # the collect has begun once a probe sent after it waits
            probe = b.pid.remote()
            if not ray.wait([probe], timeout=0.3)[0]:
                break
            assert time.monotonic() < deadline, "the collect never seemed to run"
        ray.kill(b, no_restart=False)
        got.append(ray.get(pending, timeout=120))
        second_pid = ray.get(probe, timeout=60)
        assert second_pid != first_pid  # the probe was answered by the restarted worker: the kill hit the collect
        got.append(ray.get(_collect(b, job, weights, 3)))
        ray.kill(b, no_restart=False)  # idle this time: fragment 4 starts on a fresh process
        got.append(ray.get(_collect(b, job, weights, 4), timeout=120))
        assert ray.get(b.pid.remote()) not in (first_pid, second_pid)
        for u, (g, w) in enumerate(zip(got, want, strict=True)):
            try:
                _same_fragment(g, w)
            except AssertionError as exc:
                pytest.fail(f"fragment {u}: {exc}")
        assert ray.get(b.drawn.remote(job, weights, job.ppo.rollout_steps)) == want_drawn
    finally:
        ray.kill(a)
        ray.kill(b, no_restart=True)


def test_a_fresh_worker_replays_a_job_to_the_fragment_it_is_asked_for(local_ray):
    """Fragment 3 asked of a worker that never saw the job equals the fragment 3 of a worker that collected 0-2;
    asked without the earlier weights it is refused (it could not be the same fragment)."""
    job, weights = _job()
    a, b = RolloutWorkerActor.remote(TASK), RolloutWorkerActor.remote(TASK)
    try:
        for u in range(3):
            ray.get(_collect(a, job, weights, u))
        _same_fragment(ray.get(_collect(b, job, weights, 3)), ray.get(_collect(a, job, weights, 3)))
        with pytest.raises(ray.exceptions.RayTaskError, match="needs the weights of its 3 earlier updates"):
            ray.get(b.collect.remote(job, weights[3], job.ppo.rollout_steps, 3, []))
    finally:
        ray.kill(a)
        ray.kill(b)


def test_a_worker_dead_past_its_restarts_fails_the_updates_naming_it(local_ray, monkeypatch):
    """A rollout worker that has died once more than its restarts allow ends run_updates with WorkerFailed naming
    the worker's index and the cap, instead of Ray retrying (or the coordinator waiting) for ever. The cap is 1
    here (the actor's options and WORKER_RESTARTS alike) so that two kills spend it."""
    from atdrone.service import actors

    monkeypatch.setattr(actors, "WORKER_RESTARTS", 1)
    job, _ = _job()
    learner = actors.LearnerActor.remote(LearnerSpec(ppo=job.ppo, num_e=2, num_p=4, seed=0, total_updates=2))
    healthy = RolloutWorkerActor.remote(TASK)
    doomed = RolloutWorkerActor.options(max_restarts=1, max_task_retries=1).remote(TASK)
    try:
        first = ray.get(doomed.pid.remote())
        ray.kill(doomed, no_restart=False)  # the one restart
        deadline = time.monotonic() + 60
        while ray.get(doomed.pid.remote(), timeout=60) == first:  # a probe may beat the kill to the old process
            assert time.monotonic() < deadline, "the worker was never restarted"
            time.sleep(0.2)
        ray.kill(doomed, no_restart=False)  # past the cap: dead for good
        with pytest.raises(actors.WorkerFailed, match=r"rollout worker 1 died and was restarted 1 times, the cap"):
            actors.run_updates(learner, [healthy, doomed], [job, job], 2, 64)
    finally:
        for actor in (learner, healthy, doomed):
            ray.kill(actor)


# ------------------------------------------------------------------ a rollout worker that keeps dying
class _EndsItsReader:
    """Unpickled, it ends the process reading it (os._exit): a worker handed it as its job dies before the call
    runs, and so does every restart of it that Ray retries the call on."""

    def __reduce__(self) -> tuple[Any, tuple[int]]:
        return os._exit, (3,)


def test_a_worker_that_keeps_dying_fails_the_training_naming_it_and_the_cap_instead_of_hanging(local_ray, monkeypatch):
    """Worker 1's job kills every process it reaches; Ray restarts the worker as often as its cap allows and then
    gives up, so run_updates (a generation's training) ends with an error naming worker 1 and the cap, in bounded
    time. Without a cap (max_restarts=-1) the worker restarts forever and the training never ends: the test fails.
    The workers here are capped at 2 restarts (each costs a process start); the service's class is capped at
    WORKER_RESTARTS, checked on its options."""
    import threading

    from atdrone.service import actors
    from atdrone.service.actors import WORKER_RESTARTS, LearnerActor, run_updates

    assert RolloutWorkerActor._default_options["max_restarts"] == WORKER_RESTARTS > 0
    assert RolloutWorkerActor._default_options["max_task_retries"] == WORKER_RESTARTS
    cap = 2
    monkeypatch.setattr(actors, "WORKER_RESTARTS", cap)  # what the error names
    job, _ = _job()
    spec = LearnerSpec(ppo=job.ppo, num_e=2, num_p=4, seed=0, total_updates=1)
    learner = LearnerActor.remote(spec)
    workers = [RolloutWorkerActor.options(max_restarts=cap, max_task_retries=cap).remote(TASK) for _ in range(2)]
    outcome: list[BaseException | None] = []

    def train() -> None:
        try:
            run_updates(learner, workers, [job, _EndsItsReader()], 1, 8)
            outcome.append(None)
        except BaseException as exc:  # handed to the test's thread
            outcome.append(exc)

    thread = threading.Thread(target=train, daemon=True)
    try:
        thread.start()
        thread.join(timeout=150)  # 8 restarts took 39 s on a 2-core machine under a load of 20; 2 take a quarter
        assert not thread.is_alive(), "the training still waits on a worker that keeps dying: restarts not capped"
    finally:
        for actor in (*workers, learner):
            ray.kill(actor, no_restart=True)
    (error,) = outcome
    assert error is not None
    message = str(error)
    assert "rollout worker 1" in message and f"restarted {cap} times" in message, message
