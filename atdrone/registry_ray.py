"""The registry on Ray: the named actor serving one registry file, got or created by any driver.

:func:`registry_actor` gets or creates the named actor ``RegistryActor`` (the
:class:`~atdrone.registry.Registry` class as a Ray actor, ``num_cpus=0``) in the namespace
:data:`REGISTRY_NAMESPACE`; another driver on the same cluster finds it with
:func:`find_registry_actor`. The actor holds no state beyond the sqlite file, so when it
dies Ray restarts it (``max_restarts=-1``) and it reopens the file: nothing committed is
lost. Ray is imported only when the actor is used.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

from atdrone.registry import DEFAULT_ACTOR_NAME, REGISTRY_NAMESPACE, Registry, RegistryError, default_path


@functools.cache
def _actor_class() -> Any:
    import ray

    return ray.remote(num_cpus=0, max_restarts=-1, max_task_retries=-1)(Registry)


def __getattr__(name: str) -> Any:
    """``RegistryActor`` is built on first use, so importing this module does not import Ray."""
    if name == "RegistryActor":
        return _actor_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def registry_actor(
    path: str | os.PathLike[str] | None = None,
    name: str = DEFAULT_ACTOR_NAME,
    *,
    detached: bool = False,
    node: str | None = None,
) -> Any:
    """Get or create the registry actor ``name`` in namespace ``atdrone``, serving the file ``path``.

    Lifetime: by default the actor belongs to the driver that creates it (the service
    run): it lives as long as that job, other drivers on the cluster can use it by name
    meanwhile, and the next run starts a fresh actor on the same file. ``detached=True``
    makes it outlive the driver (a standing registry service; end it with ``ray.kill``).
    An existing actor that serves a different file is refused with RegistryError.
    ``node``: a Ray node id to run the actor on (the node whose local disk holds ``path``;
    sqlite's WAL mode does not work on network file systems).

    Retries: a call in flight when the actor dies is retried after the restart, and may
    have committed before the death. Every write is therefore idempotent on a natural
    key: ``add_member`` with a ``member_id`` (callers that need exactly-once pass one, e.g.
    from :func:`new_member_id`; without one a retry registers a second id), ``add_match``
    on (run, generation, team, task, seeds), and the upserts and merges of generations and
    member updates.
    """
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    file = str(Path(path if path is not None else default_path()).resolve())
    place = {} if node is None else {"scheduling_strategy": NodeAffinitySchedulingStrategy(node, soft=False)}
    options = {"lifetime": "detached" if detached else None, **place}
    handle = _actor_class().options(name=name, namespace=REGISTRY_NAMESPACE, get_if_exists=True, **options).remote(file)
    served = ray.get(handle.db_path.remote())
    if served != file:
        raise RegistryError(f"registry actor {name!r} already serves {served}, not {file}")
    return handle


def find_registry_actor(name: str = DEFAULT_ACTOR_NAME) -> Any:
    """The running registry actor ``name`` in namespace ``atdrone`` (ValueError when there is none)."""
    import ray

    return ray.get_actor(name, namespace=REGISTRY_NAMESPACE)
