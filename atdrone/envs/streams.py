"""Counter-based random draws: every value a hash of (key, counter), vectorised over rows.

Each environment row carries its episode's key (uint64). A draw for a row is the
splitmix64 finaliser of the row's key folded with counters (the step, which call of
the step, which element), so an episode's draws depend on its own key alone, not on
which other episodes share the batch, and a whole batch draws in a few array
operations. :class:`RowStream` offers the Generator calls the simulator makes
(``uniform``, ``integers``), one row per key.
"""

from __future__ import annotations

import math
from functools import cache, lru_cache

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_UNIT = 2.0**-53
# Counter ranges, kept apart: a row's step draws count calls from 0 (the step's key is
# the episode key folded with the step number), RowStream.rows children from CHILD,
# the drones' keys for policies from DRONE_DRAWS + slot; an episode's start draws
# come from its key folded with SPAWN_DRAWS, its team events' from EVENT_DRAWS (+ 1:
# a joining drone's spawn, + 2: the member that takes a changed slot).
CHILD = 1 << 40
DRONE_DRAWS = 1 << 50
SPAWN_DRAWS = 1 << 62
EVENT_DRAWS = 3 << 61


def mix(x: np.ndarray) -> np.ndarray:
    """The splitmix64 finaliser of uint64 array ``x`` (a bijection that scrambles every bit)."""
    x = x ^ (x >> _S30)  # a new array: ``x`` is left alone; the rest works in place (integer ops, exact)
    x *= _M1
    x ^= x >> _S27
    x *= _M2
    x ^= x >> _S31
    return x


def fold(keys: np.ndarray, counter: int | np.ndarray) -> np.ndarray:
    """New keys from ``keys`` and a counter (broadcast): distinct counters give unrelated keys."""
    if isinstance(counter, int):
        return _fold_mixed(keys, _mixed_counter(counter))
    return _fold_mixed(keys, _mixed(np.atleast_1d(np.asarray(counter, dtype=np.uint64))))


def _mixed(counters: np.ndarray) -> np.ndarray:
    """:func:`fold`'s mixed form of uint64 ``counters``."""
    return mix((counters + np.uint64(1)) * _GOLDEN)


@lru_cache(maxsize=4096)
def _mixed_counter(counter: int) -> np.ndarray:
    """The mixed (1,) counter of :func:`fold` for an int counter (read-only, shared)."""
    out = _mixed(np.array([counter], dtype=np.uint64))
    out.flags.writeable = False
    return out


def _fold_mixed(keys: np.ndarray, mixed_counter: np.ndarray) -> np.ndarray:
    """:func:`fold` with its counter already mixed."""
    return mix(np.asarray(keys, dtype=np.uint64) ^ mixed_counter)


@cache
def _mixed_range(width: int) -> np.ndarray:
    """The mixed counters 0 .. width - 1 of :func:`fold` (read-only, shared)."""
    out = _mixed(np.arange(width, dtype=np.uint64))
    out.flags.writeable = False
    return out


def root_key(seed: int | None) -> np.uint64:
    """A uint64 root key from a seed (None: fresh entropy)."""
    return np.random.SeedSequence(seed).generate_state(1, np.uint64)[0]


def episode_keys(root: np.uint64, episodes: np.ndarray) -> np.ndarray:
    """Keys (n,) of episodes numbered ``episodes`` (n,) under ``root``."""
    return fold(np.full(len(episodes), root, dtype=np.uint64), np.asarray(episodes, dtype=np.uint64))


def unit(keys: np.ndarray) -> np.ndarray:
    """One uniform float64 in [0, 1) per key (53 bits of its hash)."""
    return (mix(keys) >> _S11).astype(np.float64) * _UNIT


def normal(keys: np.ndarray) -> np.ndarray:
    """One standard normal float64 per key (Box-Muller on two uniforms of the key)."""
    u1, u2 = unit(fold(keys, 0)), unit(fold(keys, 1))
    return np.sqrt(-2.0 * np.log1p(-u1)) * np.cos(2.0 * np.pi * u2)


class RowStream:
    """Random draws for n rows, row i's a function of ``keys[i]`` and the call's number only.

    Each call draws ``size`` values with ``size[0] == n``; the k-th call of the stream
    uses counter k, so the same sequence of calls gives every row the same values
    whatever the other rows are. :meth:`rows` hands a subset of rows a stream of their
    own (for redraws), without moving this stream's counter.
    """

    def __init__(self, keys: np.ndarray) -> None:
        self.keys = np.asarray(keys, dtype=np.uint64)
        self._calls = 0
        self._children = 0

    def _bits(self, size: tuple[int, ...]) -> np.ndarray:
        if size[0] != len(self.keys):
            raise ValueError(f"a RowStream of {len(self.keys)} rows cannot draw size {size}")
        call = fold(self.keys, self._calls)
        self._calls += 1
        return _fold_mixed(call[:, None], _mixed_range(math.prod(size[1:]))).reshape(size)

    def random(self, size: tuple[int, ...]) -> np.ndarray:
        """Uniform floats in [0, 1) of shape ``size``."""
        return (self._bits(size) >> _S11).astype(np.float64) * _UNIT

    def uniform(self, low: float, high: float, size: tuple[int, ...]) -> np.ndarray:
        """Uniform floats in [low, high) of shape ``size``."""
        return low + (high - low) * self.random(size)

    def integers(self, low: int, high: int, size: tuple[int, ...]) -> np.ndarray:
        """Uniform integers in [low, high) of shape ``size``."""
        return low + np.floor(self.random(size) * (high - low)).astype(np.int64)

    def rows(self, mask: np.ndarray) -> RowStream:
        """A stream for the rows where ``mask`` is true, apart from this one and from earlier children."""
        child = RowStream(fold(self.keys[mask], CHILD + self._children))
        self._children += 1
        return child
