"""What the parts of a flight call on each other, declared once for the type checker.

:class:`~atdrone.deploy.loop.Flight` is built from parts (:class:`~atdrone.deploy.backup.Backups`,
:class:`~atdrone.deploy.landing.Landing`, :class:`~atdrone.deploy.sequence.Sequencing`), each of
which calls methods that the flight itself or another part provides. :class:`FlightHooks`, their
common base, declares those methods only while type checking. At run time it is empty: a
runtime stub in one part would stand before a later part's real method in the flight's bases
and shadow it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from atdrone.deploy.shield import ShieldDecision


class FlightHooks:
    """The methods a flight's parts call on the flight (see the module docstring)."""

    if TYPE_CHECKING:
        # the flight's own (atdrone.deploy.loop.Flight)
        def _begin_tick(self, step: int = -1) -> float: ...

        def measured(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...

        def _shield(
            self,
            pos: np.ndarray,
            age: np.ndarray,
            setpoints: np.ndarray,
            vel: np.ndarray | None = None,
            policy_late: float = 0.0,
        ) -> ShieldDecision: ...

        def _apply(self, decision: ShieldDecision) -> bool: ...

        def _hold_tick(self, first: Callable[[], None] | None = None) -> bool: ...

        def _log_tick(
            self,
            t: float,
            step: int,
            pos: np.ndarray,
            yaw: np.ndarray,
            decision: ShieldDecision,
            latency: dict[str, float],
            virtual_e: np.ndarray | None,
        ) -> None: ...

        # the landing part's (atdrone.deploy.landing.Landing)
        def _land(self, names: Sequence[str]) -> None: ...

        def _set_state(self, names: Sequence[str], state: str) -> None: ...

        def _airborne(self) -> np.ndarray: ...

        def _landing_time(self) -> float: ...

        def _touchdown(self, pos: np.ndarray) -> None: ...

        # the sequencing part's (atdrone.deploy.sequence.Sequencing)
        def _fence(self) -> tuple[np.ndarray, np.ndarray]: ...
