"""The environment configurator: typed, validated task documents (SPEC section 7).

A task document is one JSON object in three parts, ``players``, ``site`` and ``task``.
Every key is documented on the dataclass that holds it. ``load_task`` accepts one of
the paper's task names ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o"), a path to a JSON
file, or an already-parsed mapping. Any problem raises :class:`ConfigError` whose
message starts with the JSON path of the offending value, e.g.
``players.velocity_p: must be > 0, got -0.3``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from atdrone.errors import UserError

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
TASK_NAMES = ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")
# upper bounds of sizes that allocate memory (the paper's tasks use 4 pursuers, 3 evaders, 5 obstacles, 1000 steps)
MAX_DRONES = 64
MAX_OBSTACLES = 256
MAX_HORIZON = 100_000
MAX_SEED = 2**32 - 1  # numpy's and the evaluation's seed range


class ConfigError(UserError, ValueError):
    """A configuration document is malformed; ``path`` names the offending field."""

    def __init__(self, path: str | None, message: str) -> None:
        """``path`` names the field ("" for the document itself); None for an error about a file or a
        command-line argument, whose message then stands alone (no field to name)."""
        self.path = "<root>" if path is None or path == "" else path
        super().__init__(message if path is None else f"{self.path}: {message}")


def _positive(value: float) -> str | None:
    return None if value > 0 else f"must be > 0, got {value!r}"


def _non_negative(value: float) -> str | None:
    return None if value >= 0 else f"must be >= 0, got {value!r}"


def _between(low: int, high: int) -> Any:
    """A check that an integer lies in [low, high] (sizes that allocate memory have an upper bound)."""

    def check(value: int) -> str | None:
        return None if low <= value <= high else f"must be between {low} and {high:,}, got {value:,}"

    return check


def _interval(value: tuple[float, float]) -> str | None:
    lo, hi = value
    return None if lo <= hi else f"must be [low, high] with low <= high, got {list(value)!r}"


OPTIONAL = {"empty_ok": True}  # field metadata: an empty string is allowed and means "none"


def _check(fn: Any) -> dict[str, Any]:
    return {"check": fn}


@dataclass(frozen=True)
class SpawnRegion:
    """Where one kind of drone appears: drone i at x = U(x) + x_step * i, y = U(y).

    For evaders a single x draw is shared by the group (SPEC section 1).
    """

    x: tuple[float, float] = field(metadata=_check(_interval))
    y: tuple[float, float] = field(metadata=_check(_interval))
    x_step: float = field(default=0.0, metadata=_check(_non_negative))


@dataclass(frozen=True)
class RespawnRegion:
    """Spawn regions of the pursuers and of the evaders."""

    pursuer: SpawnRegion
    evader: SpawnRegion


@dataclass(frozen=True)
class Players:
    """Who plays: counts, speeds, perception, spawn regions and the partner zoo."""

    num_p: int = field(metadata=_check(_between(2, MAX_DRONES)))
    num_e: int = field(metadata=_check(_between(1, MAX_DRONES)))
    num_ctrl: int = field(metadata=_check(_between(1, MAX_DRONES)))
    num_unctrl: int = field(metadata=_check(_non_negative))
    respawn_region: RespawnRegion
    random_respawn: bool = True
    reception_range: float = field(default=2.0, metadata=_check(_positive))
    velocity_p: float = field(default=0.3, metadata=_check(_positive))
    velocity_e: float = field(default=0.6, metadata=_check(_positive))
    unseen_drones: str = "zoo3"


@dataclass(frozen=True)
class Boundary:
    """The arena: an axis-aligned rectangle with its origin at a corner (metres)."""

    width: float = field(metadata=_check(_positive))
    height: float = field(metadata=_check(_positive))


@dataclass(frozen=True)
class Box:
    """An axis-aligned box obstacle spanning x and y (metres)."""

    type: Literal["box"]
    x: tuple[float, float] = field(metadata=_check(_interval))
    y: tuple[float, float] = field(metadata=_check(_interval))


@dataclass(frozen=True)
class Disc:
    """A disc obstacle (a cylinder seen from above)."""

    type: Literal["disc"]
    center: tuple[float, float]
    radius: float = field(metadata=_check(_positive))


@dataclass(frozen=True)
class Site:
    """The arena boundary and its named obstacles."""

    boundary: Boundary
    obstacles: dict[str, Box | Disc] = field(default_factory=dict)


@dataclass(frozen=True)
class Proximity:
    """Optional teammate-proximity penalties: each band is [low, high, penalty]."""

    enabled: bool = False
    bands: tuple[tuple[float, float, float], ...] = (
        (0.2, 0.25, -1.0),
        (0.25, 0.3, -0.1),
        (0.3, 0.4, -0.01),
    )


@dataclass(frozen=True)
class Reward:
    """Coefficients of the shared team reward (SPEC section 6).

    capture: per evader captured. approach: weight of the shaping term, the reduction
    of each uncaptured evader's nearest-pursuer distance divided by approach_scale.
    collision: added once in a step with any collision.
    """

    capture: float = 10.0
    approach: float = 1.0
    approach_scale: float = field(default=0.3, metadata=_check(_positive))
    collision: float = -10.0
    proximity: Proximity = field(default_factory=Proximity)


@dataclass(frozen=True)
class TaskSpec:
    """Episode rules: capture and safety radii, horizon, frame rate, rewards."""

    task_name: str
    capture_range: float = field(default=0.2, metadata=_check(_positive))
    safe_radius: float = field(default=0.1, metadata=_check(_positive))
    collision_distance: float = field(default=0.2, metadata=_check(_positive))
    task_horizon: int = field(default=1000, metadata=_check(_between(1, MAX_HORIZON)))
    fps: int = field(default=10, metadata=_check(_between(1, 1000)))
    collision_ends_episode: bool = True
    reward: Reward = field(default_factory=Reward)


@dataclass(frozen=True)
class TaskConfig:
    """A whole validated task document."""

    players: Players
    site: Site
    task: TaskSpec

    @property
    def name(self) -> str:
        return self.task.task_name

    @property
    def dt(self) -> float:
        return 1.0 / self.task.fps

    def to_dict(self) -> dict[str, Any]:
        """The document as plain JSON-compatible data (round-trips through load_task)."""
        return _to_jsonable(self)


def _to_jsonable(value: Any) -> Any:
    if dataclasses.is_dataclass(value):
        return {f.name: _to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: _to_jsonable(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [_to_jsonable(v) for v in value]
    return value


def _join(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


def _describe(value: Any) -> str:
    text = json.dumps(value) if isinstance(value, str | int | float | bool | type(None)) else None
    return text if text is not None else type(value).__name__


def _parse(tp: Any, value: Any, path: str) -> Any:
    """Convert JSON data to ``tp``, raising ConfigError naming ``path`` on mismatch."""
    origin = typing.get_origin(tp)
    if tp is Any:  # validated later by whoever owns the value
        return value
    if dataclasses.is_dataclass(tp):
        return _parse_dataclass(tp, value, path)
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(path, f"must be one of {list(typing.get_args(tp))}, got {_describe(value)}")
        return value
    if origin in (typing.Union, types.UnionType):
        options = tuple(a for a in typing.get_args(tp) if a is not type(None))
        if len(options) == 1 and len(typing.get_args(tp)) == 2:  # X | None: null means none
            return None if value is None else _parse(options[0], value, path)
        return _parse_tagged(options, value, path)
    if origin is dict:
        _, val_tp = typing.get_args(tp)
        if not isinstance(value, Mapping):
            raise ConfigError(path, f"must be an object, got {_describe(value)}")
        return {str(k): _parse(val_tp, v, _join(path, str(k))) for k, v in value.items()}
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list | tuple):
            raise ConfigError(path, f"must be a list, got {_describe(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_parse(args[0], v, _join(path, i)) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(path, f"must be a list of {len(args)} items, got {len(value)}")
        return tuple(_parse(a, v, _join(path, i)) for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(path, f"must be true or false, got {_describe(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(path, f"must be an integer, got {_describe(value)}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(path, f"must be a number, got {_describe(value)}")
        try:
            number = float(value)
        except OverflowError:  # a JSON integer literal beyond the float range
            raise ConfigError(path, "must be finite, got an integer too large for a float") from None
        if not math.isfinite(number):
            raise ConfigError(path, f"must be finite, got {value!r}")
        return number
    if tp is str:
        if not isinstance(value, str) or not value:
            raise ConfigError(path, f"must be a non-empty string, got {_describe(value)}")
        return value
    raise TypeError(f"unsupported schema type {tp!r}")  # pragma: no cover - schema bug


def _parse_tagged(options: tuple[Any, ...], value: Any, path: str) -> Any:
    """Pick the union member whose ``type`` literal matches the document's ``type``."""
    tags = {typing.get_args(typing.get_type_hints(o)["type"])[0]: o for o in options}
    if not isinstance(value, Mapping):
        raise ConfigError(path, f"must be an object, got {_describe(value)}")
    if "type" not in value:
        raise ConfigError(_join(path, "type"), f"missing key (one of {sorted(tags)})")
    if not isinstance(value["type"], str) or value["type"] not in tags:
        raise ConfigError(_join(path, "type"), f"must be one of {sorted(tags)}, got {_describe(value['type'])}")
    return _parse(tags[value["type"]], value, path)


def _parse_dataclass(cls: Any, value: Any, path: str) -> Any:
    if not isinstance(value, Mapping):
        raise ConfigError(path, f"must be an object, got {_describe(value)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for key in value:
        if key not in fields:
            raise ConfigError(_join(path, str(key)), f"unknown key (known: {', '.join(fields)})")
    kwargs = {}
    for name, f in fields.items():
        sub = _join(path, name)
        if name not in value:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(sub, "missing key")
            continue
        if value[name] == "" and f.metadata.get("empty_ok"):  # an empty string that means "none"
            kwargs[name] = ""
            continue
        parsed = _parse(hints[name], value[name], sub)
        check = f.metadata.get("check")
        if check is not None and (problem := check(parsed)) is not None:
            raise ConfigError(sub, problem)
        kwargs[name] = parsed
    return cls(**kwargs)


def _box_overlaps(a: tuple[tuple[float, float], tuple[float, float]], ob: Box | Disc, margin: float) -> bool:
    (x0, x1), (y0, y1) = a
    if isinstance(ob, Box):
        return x0 < ob.x[1] + margin and x1 > ob.x[0] - margin and y0 < ob.y[1] + margin and y1 > ob.y[0] - margin
    cx, cy = ob.center
    dx = max(x0 - cx, 0.0, cx - x1)
    dy = max(y0 - cy, 0.0, cy - y1)
    return math.hypot(dx, dy) < ob.radius + margin


def spawn_boxes(region: SpawnRegion, count: int) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """The x/y ranges in which each of ``count`` drones can spawn."""
    return [((region.x[0] + region.x_step * i, region.x[1] + region.x_step * i), region.y) for i in range(count)]


def _validate_semantics(cfg: TaskConfig) -> None:
    p, site, task = cfg.players, cfg.site, cfg.task
    if p.num_ctrl + p.num_unctrl != p.num_p:
        raise ConfigError(
            "players.num_ctrl",
            f"num_ctrl + num_unctrl must equal num_p, got {p.num_ctrl} + {p.num_unctrl} != {p.num_p}",
        )
    if p.num_p < 2:
        raise ConfigError("players.num_p", f"must be >= 2 (a team), got {p.num_p}")
    if len(site.obstacles) > MAX_OBSTACLES:
        raise ConfigError("site.obstacles", f"at most {MAX_OBSTACLES} obstacles, got {len(site.obstacles):,}")
    w, h = site.boundary.width, site.boundary.height
    side = min(w, h)
    for key in ("collision_distance", "capture_range"):  # as wide as the arena: every episode ends at once
        if getattr(task, key) >= side:
            raise ConfigError(
                f"task.{key}",
                f"must be less than the arena's smaller side ({side:g} m of the {w:g} x {h:g} m arena), "
                f"got {getattr(task, key):g}",
            )
    if 2 * task.safe_radius >= side:
        raise ConfigError(
            "task.safe_radius",
            f"must be less than half the arena's smaller side ({side / 2:g} m), got {task.safe_radius:g}",
        )
    for name, ob in site.obstacles.items():
        path = f"site.obstacles.{name}"
        if isinstance(ob, Box):
            inside = ob.x[0] >= 0 and ob.x[1] <= w and ob.y[0] >= 0 and ob.y[1] <= h
            if ob.x[0] == ob.x[1] or ob.y[0] == ob.y[1]:
                raise ConfigError(path, f"box has zero width or height: x {list(ob.x)}, y {list(ob.y)}")
        else:
            cx, cy = ob.center
            inside = ob.radius <= cx <= w - ob.radius and ob.radius <= cy <= h - ob.radius
        if not inside:
            raise ConfigError(path, f"obstacle lies outside the {w} x {h} arena")
    margin = task.safe_radius
    for kind, region, count in (
        ("pursuer", p.respawn_region.pursuer, p.num_p),
        ("evader", p.respawn_region.evader, p.num_e),
    ):
        path = f"players.respawn_region.{kind}"
        for i, ((x0, x1), (y0, y1)) in enumerate(spawn_boxes(region, count)):
            if x0 < margin or x1 > w - margin or y0 < margin or y1 > h - margin:
                raise ConfigError(
                    path,
                    f"{kind} {i} may spawn within {margin} m of the arena wall or outside it: "
                    f"x [{x0:g}, {x1:g}], y [{y0:g}, {y1:g}]",
                )
            for name, ob in site.obstacles.items():
                if _box_overlaps(((x0, x1), (y0, y1)), ob, margin):
                    raise ConfigError(path, f"{kind} {i} spawn region overlaps obstacle {name!r}")
    for i, (lo, hi, _) in enumerate(task.reward.proximity.bands):
        if not 0 <= lo < hi:
            raise ConfigError(f"task.reward.proximity.bands[{i}]", f"must have 0 <= low < high, got [{lo}, {hi}]")


def parse_task(document: Any) -> TaskConfig:
    """Validate a parsed JSON document into a TaskConfig."""
    cfg = _parse(TaskConfig, document, "")
    _validate_semantics(cfg)
    return cfg


def parse_document(schema: Any, document: Any, path: str = "") -> Any:
    """Validate JSON data against a dataclass ``schema``; errors name the JSON path."""
    return _parse(schema, document, path)


def repo_path(path: str | Path) -> Path:
    """An absolute path as given; a relative one taken from the repository root (beside configs/)."""
    path = Path(path)
    return path if path.is_absolute() else CONFIG_DIR.parent / path


def read_document(name_or_path: str | Path, kind: str, names: tuple[str, ...] = ()) -> Any:
    """Parse the JSON of configs/<kind>/<name>.json for a known name, else of a path."""
    text = str(name_or_path)
    path = CONFIG_DIR / kind / f"{text}.json" if text in names else Path(text)
    if not path.is_file():
        names = names or tuple(sorted(p.stem for p in (CONFIG_DIR / kind).glob("*.json")))
        known = f" (known: {', '.join(names)})" if names else ""
        noun = kind.removesuffix("s")
        raise ConfigError(None, f"no {noun} named {text!r}{known} and no such file")
    return read_json(path)


MAX_DOCUMENT_BYTES = 16 * 2**20  # a config is a few KB; a bigger file is not one


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    seen: dict[str, Any] = {}
    for key, value in pairs:
        if key in seen:
            raise ConfigError(key, "appears twice in one JSON object (which one was meant?)")
        seen[key] = value
    return seen


def read_json(path: str | Path) -> Any:
    """The JSON of a file a user gave: ConfigError for a missing or oversized file, bytes that are not
    UTF-8, invalid or too deeply nested JSON, and a key given twice in one object (never last-wins)."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_DOCUMENT_BYTES:
            raise ConfigError(None, f"{path} is over {MAX_DOCUMENT_BYTES // 2**20} MB: not a config document")
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(None, f"{path} is not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    except IsADirectoryError:
        raise ConfigError(None, f"{path} is a directory, not a JSON file") from None
    except OSError as exc:
        raise ConfigError(None, f"cannot read {path}: {exc.strerror or exc}") from None
    try:
        return json.loads(text, object_pairs_hook=_no_duplicates)
    except json.JSONDecodeError as exc:
        raise ConfigError(None, f"{path} is not valid JSON: {exc}") from None
    except RecursionError:
        raise ConfigError(None, f"{path} is nested too deeply to be a config document") from None
    except ConfigError as exc:
        raise ConfigError(exc.path, f"{exc.args[0].split(': ', 1)[1]} (in {path})") from None
    except ValueError as exc:  # a number of more digits than Python converts (4300)
        raise ConfigError(None, f"{path} is not a config: {str(exc).split(';')[0]}") from None


def read_object(name_or_path: str | Path, kind: str, names: tuple[str, ...] = ()) -> dict[str, Any]:
    """:func:`read_document` of a document that must be one JSON object (a config), else ConfigError."""
    document = read_document(name_or_path, kind, names)
    if not isinstance(document, dict):
        got = _describe(document)
        raise ConfigError(None, f"{name_or_path} must hold one JSON object (a config), got {got}")
    return document


def load_config(schema: Any, path_or_doc: str | Path | Mapping[str, Any], kind: str, **overrides: Any) -> Any:
    """A document of configs/<kind>/ (a path or a mapping), with non-None overrides, validated against ``schema``."""
    doc = dict(path_or_doc) if isinstance(path_or_doc, Mapping) else read_object(path_or_doc, kind)
    doc.update({k: v for k, v in overrides.items() if v is not None})
    return parse_document(schema, doc)


def check_task_field(task: str, path: str = "task") -> TaskConfig:
    """Load the task a config names; its errors are reported under ``path``."""
    try:
        return load_task(task)
    except ConfigError as exc:
        raise ConfigError(path, str(exc)) from None


def require_at_least(cfg: Any, names: tuple[str, ...], minimum: float = 1) -> None:
    """ConfigError naming the first of ``names`` whose value is below ``minimum``."""
    for name in names:
        if getattr(cfg, name) < minimum:
            raise ConfigError(name, f"must be >= {minimum}, got {getattr(cfg, name)}")


def require_at_most(cfg: Any, limits: Mapping[str, float]) -> None:
    """ConfigError naming the first field of ``limits`` whose value is above its limit."""
    for name, limit in limits.items():
        if getattr(cfg, name) > limit:
            raise ConfigError(name, f"must be <= {limit:,}, got {getattr(cfg, name):,}")


def check_seed(value: int, path: str = "seed") -> None:
    """ConfigError unless ``value`` is a seed numpy and torch take: 0 <= seed <= MAX_SEED (2**32 - 1)."""
    if not 0 <= value <= MAX_SEED:
        raise ConfigError(path, f"must be between 0 and 2**32 - 1, got {value}")


RUN_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,99}")


def check_run_name(name: str, path: str = "name") -> None:
    """A run name is a folder under out_dir and part of MLflow names: letters, digits, '.', '_', '-' only,
    not starting with '.', at most 100 characters (so never '..', '/', ':' or an absolute path)."""
    if not RUN_NAME.fullmatch(name):
        raise ConfigError(
            path, f"{name!r} is not a run name: use letters, digits, '.', '_' and '-' (not first '.'), 1-100 characters"
        )


def load_task(name_or_path: str | Path | Mapping[str, Any] | TaskConfig) -> TaskConfig:
    """Load a task by paper name, JSON path or mapping; raise ConfigError when invalid."""
    if isinstance(name_or_path, TaskConfig):
        return name_or_path
    if isinstance(name_or_path, Mapping):
        return parse_task(name_or_path)
    return parse_task(read_document(name_or_path, "tasks", TASK_NAMES))
