"""The task configurator: the four paper tasks, and malformed documents rejected by path.

Every malformed document must raise :class:`ConfigError` whose message starts with the
JSON path of the offending field; no KeyError/TypeError/AttributeError may escape.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import types
import typing
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from atdrone.config import CONFIG_DIR, TASK_NAMES, ConfigError, TaskConfig, load_task

Path_ = tuple[str | int, ...]

# SPEC section 1, obstacle coordinates: (kind, x-range or centre, y-range or radius).
SPEC_OBSTACLES = {
    "4p2e1o": [("box", (1.0, 2.5), (2.45, 2.55))],
    "4p2e3o": [
        ("box", (1.0, 1.4), (1.3, 1.7)),
        ("box", (1.0, 1.4), (3.3, 3.7)),
        ("disc", (2.4, 2.5), 0.2),
    ],
    "4p2e5o": [
        ("box", (0.9, 1.55), (1.0, 1.1)),
        ("box", (2.05, 2.7), (1.0, 1.1)),
        ("box", (1.4, 2.2), (2.45, 2.55)),
        ("box", (0.9, 1.55), (3.9, 4.0)),
        ("box", (2.05, 2.7), (3.9, 4.0)),
    ],
}
SPEC_OBSTACLES["4p3e5o"] = SPEC_OBSTACLES["4p2e5o"]

# Keys a document may leave out (they have defaults). Obstacle names are "<obstacle>",
# list items "[]". Deleting any other key or list item must be rejected.
OPTIONAL = {
    "players.random_respawn",
    "players.reception_range",
    "players.velocity_p",
    "players.velocity_e",
    "players.unseen_drones",
    "players.respawn_region.pursuer.x_step",
    "players.respawn_region.evader.x_step",
    "site.obstacles",
    "site.obstacles.<obstacle>",
    "task.capture_range",
    "task.safe_radius",
    "task.collision_distance",
    "task.task_horizon",
    "task.fps",
    "task.collision_ends_episode",
    "task.reward",
    "task.reward.capture",
    "task.reward.approach",
    "task.reward.approach_scale",
    "task.reward.collision",
    "task.reward.proximity",
    "task.reward.proximity.enabled",
    "task.reward.proximity.bands",
    "task.reward.proximity.bands[]",
}


def task_document(name: str) -> dict[str, Any]:
    return json.loads((CONFIG_DIR / "tasks" / f"{name}.json").read_text())


def fmt(path: Path_) -> str:
    """The JSON path as ConfigError spells it: a.b[0].c."""
    out = ""
    for key in path:
        out += f"[{key}]" if isinstance(key, int) else (f".{key}" if out else key)
    return out


def pattern(path: Path_) -> str:
    """The path with obstacle names and list indices made generic."""
    generic: list[str | int] = []
    for i, key in enumerate(path):
        if path[:i] == ("site", "obstacles"):
            key = "<obstacle>"
        generic.append("[]" if isinstance(key, int) else key)
    return "".join("[]" if k == "[]" else (f".{k}" if j else str(k)) for j, k in enumerate(generic))


def walk(node: Any, path: Path_ = ()) -> Iterator[Path_]:
    """Every key and list item below ``node``, parents before children."""
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        yield (*path, key)
        yield from walk(value, (*path, key))


def get(doc: Any, path: Path_) -> Any:
    for key in path:
        doc = doc[key]
    return doc


def is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_float_field(path: Path_, value: Any) -> bool:
    """Numbers in the task files; the integer fields are the counts, the horizon and fps."""
    return isinstance(value, float) or (
        is_int(value) and path[-1] not in ("num_p", "num_e", "num_ctrl", "num_unctrl", "task_horizon", "fps")
    )


# Canonical values of the wrong type for each kind of field.
WRONG_FOR_FLOAT = ["0.3", True, False, None, [0.3], {"value": 0.3}]
WRONG_FOR_INT = [2.5, True, False, "4", None, [4], {"value": 4}]
WRONG_FOR_BOOL = [1, 0, "true", None, [True], {"value": True}]
WRONG_FOR_STR = [5, 0.5, True, None, "", ["zoo3"], {"value": "zoo3"}]
WRONG_FOR_LIST = ["1.0, 2.0", 1.0, True, None, {"low": 1.0, "high": 2.0}]
WRONG_FOR_OBJECT = [[], [1, 2], "object", 1, 1.5, True, None]


def wrong_values(path: Path_, value: Any) -> list[Any]:
    if isinstance(value, bool):
        return WRONG_FOR_BOOL
    if isinstance(value, dict):
        return WRONG_FOR_OBJECT
    if isinstance(value, list):
        return WRONG_FOR_LIST
    if isinstance(value, str):
        return [*WRONG_FOR_STR, "cone"] if path[-1] == "type" else WRONG_FOR_STR
    return WRONG_FOR_FLOAT if is_float_field(path, value) else WRONG_FOR_INT


def wrong_value_strategy(path: Path_, value: Any) -> st.SearchStrategy[Any]:
    """Random JSON values that are not of the field's type."""
    scalars = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=False), st.text(max_size=5))
    lists = st.lists(scalars, max_size=3)
    objects = st.dictionaries(st.text(max_size=5), scalars, max_size=3)
    if isinstance(value, bool):
        return st.one_of(st.none(), st.integers(), st.floats(), st.text(max_size=5), lists, objects)
    if isinstance(value, dict):
        return st.one_of(scalars, lists)
    if isinstance(value, list):
        return st.one_of(scalars, objects)
    if isinstance(value, str):
        strings = st.text(max_size=8).filter(lambda s: s not in ("box", "disc")) if path[-1] == "type" else st.just("")
        return st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), lists, objects, strings)
    non_numbers = st.one_of(st.none(), st.booleans(), st.text(max_size=5), lists, objects)
    if is_float_field(path, value):
        return non_numbers
    return st.one_of(non_numbers, st.floats().filter(lambda f: not float(f).is_integer()))


def assert_rejected_at(doc: Any, path: str) -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_task(doc)
    assert str(info.value).startswith(f"{path}: "), f"expected an error at {path!r}, got {info.value}"
    assert info.value.path == path
    return info.value


def mutate(doc: dict[str, Any], path: Path_, set_to: Any = None, delete: bool = False) -> dict[str, Any]:
    doc = copy.deepcopy(doc)
    parent = get(doc, path[:-1])
    if delete:
        del parent[path[-1]]
    else:
        parent[path[-1]] = set_to
    return doc


def check_deletion(doc: dict[str, Any], path: Path_) -> None:
    """Delete ``path``: optional keys load, required ones are named in the error."""
    mutated = mutate(doc, path, delete=True)
    if pattern(path) in OPTIONAL:
        assert isinstance(load_task(mutated), TaskConfig)
    elif isinstance(path[-1], int):  # an item of a fixed-length list: the list is the wrong length
        assert_rejected_at(mutated, fmt(path[:-1]))
    else:
        error = assert_rejected_at(mutated, fmt(path))
        assert "missing key" in str(error)


def check_wrong_type(doc: dict[str, Any], path: Path_, value: Any) -> None:
    assert_rejected_at(mutate(doc, path, set_to=value), fmt(path))


def check_unknown_key(doc: dict[str, Any], mapping: Path_, key: str, value: Any) -> None:
    """An unknown key beside the known ones in the object at ``mapping``."""
    mutated = copy.deepcopy(doc)
    get(mutated, mapping)[key] = value
    assert_rejected_at(mutated, fmt((*mapping, key)))


# ----------------------------------------------------------------- the paper's tasks
@pytest.mark.parametrize("name", TASK_NAMES)
def test_paper_task_loads_by_name_and_path_identically(name: str) -> None:
    path = CONFIG_DIR / "tasks" / f"{name}.json"
    by_name = load_task(name)
    assert by_name.name == name
    assert load_task(path) == by_name
    assert load_task(str(path)) == by_name
    assert load_task(by_name) is by_name


@pytest.mark.parametrize("name", TASK_NAMES)
def test_paper_task_round_trips_through_to_dict(name: str) -> None:
    cfg = load_task(name)
    document = cfg.to_dict()
    assert load_task(document) == cfg
    assert load_task(json.loads(json.dumps(document))) == cfg
    assert document == task_document(name)


@pytest.mark.parametrize("name", TASK_NAMES)
def test_paper_task_matches_spec_numbers(name: str) -> None:
    cfg = load_task(name)
    p, t = cfg.players, cfg.task
    assert (p.num_p, p.num_e, p.num_ctrl, p.num_unctrl) == (4, int(name[2]), 2, 2)
    assert (cfg.site.boundary.width, cfg.site.boundary.height) == (3.6, 5.0)
    assert (p.velocity_p, p.velocity_e, p.reception_range) == (0.3, 0.6, 2.0)
    assert (t.capture_range, t.safe_radius, t.collision_distance) == (0.2, 0.1, 0.2)
    assert (t.task_horizon, t.fps, cfg.dt) == (1000, 10, 0.1)
    assert t.collision_ends_episode and p.random_respawn
    r = t.reward
    assert (r.capture, r.approach, r.approach_scale, r.collision) == (10.0, 1.0, 0.3, -10.0)
    assert not r.proximity.enabled
    assert r.proximity.bands == ((0.2, 0.25, -1.0), (0.25, 0.3, -0.1), (0.3, 0.4, -0.01))
    rp, re = p.respawn_region.pursuer, p.respawn_region.evader
    assert (rp.x, rp.y, rp.x_step) == ((0.2, 1.2), (0.2, 0.8), 0.6)
    assert (re.x, re.y, re.x_step) == ((0.2, 2.6), (4.2, 4.8), 0.4)


@pytest.mark.parametrize("name", TASK_NAMES)
def test_paper_task_obstacles_match_spec_coordinates(name: str) -> None:
    shapes = []
    for ob in load_task(name).site.obstacles.values():
        shapes.append(("box", ob.x, ob.y) if ob.type == "box" else ("disc", ob.center, ob.radius))
    assert sorted(shapes) == sorted(SPEC_OBSTACLES[name])


def test_omitted_optional_keys_take_spec_defaults() -> None:
    doc = {
        "players": {
            "num_p": 4,
            "num_e": 2,
            "num_ctrl": 2,
            "num_unctrl": 2,
            "respawn_region": {
                "pursuer": {"x": [0.2, 1.2], "y": [0.2, 0.8], "x_step": 0.6},
                "evader": {"x": [0.2, 2.6], "y": [4.2, 4.8], "x_step": 0.4},
            },
        },
        "site": {"boundary": {"width": 3.6, "height": 5.0}},
        "task": {"task_name": "empty"},
    }
    cfg = load_task(doc)
    full = task_document("4p2e1o")
    full["site"]["obstacles"] = {}
    full["task"]["task_name"] = "empty"
    assert cfg == load_task(full)


# ------------------------------------------------------- malformed documents by name
def test_missing_key_is_named() -> None:
    doc = task_document("4p2e1o")
    del doc["players"]["num_e"]
    assert "missing key" in str(assert_rejected_at(doc, "players.num_e"))


def test_missing_obstacle_type_is_named() -> None:
    doc = task_document("4p2e1o")
    del doc["site"]["obstacles"]["bar"]["type"]
    assert_rejected_at(doc, "site.obstacles.bar.type")


def test_unknown_key_is_named() -> None:
    doc = task_document("4p2e1o")
    doc["task"]["reward"]["bonus"] = 1.0
    assert "unknown key" in str(assert_rejected_at(doc, "task.reward.bonus"))


def test_unknown_top_level_key_is_named() -> None:
    doc = task_document("4p2e1o")
    doc["extras"] = {}
    assert_rejected_at(doc, "extras")


def test_string_for_number_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["players"]["velocity_p"] = "0.3"
    assert "number" in str(assert_rejected_at(doc, "players.velocity_p"))


def test_bool_for_int_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["players"]["num_p"] = True
    assert "integer" in str(assert_rejected_at(doc, "players.num_p"))


def test_bool_for_number_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["task"]["capture_range"] = False
    assert_rejected_at(doc, "task.capture_range")


def test_fraction_for_int_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["task"]["task_horizon"] = 100.5
    assert_rejected_at(doc, "task.task_horizon")


def test_list_for_object_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["site"]["boundary"] = [3.6, 5.0]
    assert "object" in str(assert_rejected_at(doc, "site.boundary"))


def test_number_for_bool_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["task"]["collision_ends_episode"] = 1
    assert_rejected_at(doc, "task.collision_ends_episode")


def test_negative_speed_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["players"]["velocity_e"] = -0.6
    assert "> 0" in str(assert_rejected_at(doc, "players.velocity_e"))


def test_zero_radius_is_rejected() -> None:
    doc = task_document("4p2e3o")
    doc["site"]["obstacles"]["cylinder"]["radius"] = 0
    assert_rejected_at(doc, "site.obstacles.cylinder.radius")


@pytest.mark.parametrize("field", ["capture_range", "safe_radius", "collision_distance", "task_horizon", "fps"])
def test_non_positive_task_numbers_are_rejected(field: str) -> None:
    doc = task_document("4p2e1o")
    doc["task"][field] = 0
    assert_rejected_at(doc, f"task.{field}")


def test_controlled_plus_partner_count_must_equal_pursuers() -> None:
    doc = task_document("4p2e1o")
    doc["players"]["num_unctrl"] = 1
    error = assert_rejected_at(doc, "players.num_ctrl")
    assert "num_unctrl" in str(error) and "num_p" in str(error)


def test_single_pursuer_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["players"].update(num_p=1, num_ctrl=1, num_unctrl=0)
    assert_rejected_at(doc, "players.num_p")


@pytest.mark.parametrize(
    ("name", "obstacle", "change"),
    [
        ("4p2e1o", "bar", {"x": [3.0, 3.8]}),
        ("4p2e1o", "bar", {"y": [-0.1, 0.05]}),
        ("4p2e3o", "cylinder", {"center": [3.5, 2.5]}),
        ("4p2e3o", "cylinder", {"center": [2.4, 4.9]}),
    ],
)
def test_obstacle_outside_arena_is_rejected(name: str, obstacle: str, change: dict[str, Any]) -> None:
    doc = task_document(name)
    doc["site"]["obstacles"][obstacle].update(change)
    assert "outside" in str(assert_rejected_at(doc, f"site.obstacles.{obstacle}"))


@pytest.mark.parametrize(
    ("shape", "region"),
    [
        ({"type": "box", "x": [0.5, 0.7], "y": [0.4, 0.6]}, "pursuer"),
        ({"type": "disc", "center": [2.0, 0.5], "radius": 0.1}, "pursuer"),
        ({"type": "box", "x": [1.0, 1.2], "y": [4.4, 4.5]}, "evader"),
        # within safe_radius of the evader region (y from 4.2) without touching it
        ({"type": "box", "x": [1.0, 1.2], "y": [4.0, 4.15]}, "evader"),
    ],
)
def test_spawn_region_overlapping_obstacle_is_rejected(shape: dict[str, Any], region: str) -> None:
    doc = task_document("4p2e1o")
    doc["site"]["obstacles"]["intruder"] = shape
    error = assert_rejected_at(doc, f"players.respawn_region.{region}")
    assert "intruder" in str(error)


@pytest.mark.parametrize(
    ("region", "change"),
    [
        ("evader", {"y": [4.2, 5.2]}),
        ("evader", {"x_step": 0.6}),  # with 3 evaders, evader 2 at x 1.4-3.8
        ("pursuer", {"x_step": 1.2}),  # pursuer 3 at x 3.8-4.8
        ("pursuer", {"y": [0.0, 0.8]}),  # touches the bottom wall
    ],
)
def test_spawn_region_outside_arena_is_rejected(region: str, change: dict[str, Any]) -> None:
    doc = task_document("4p2e1o")
    doc["players"]["respawn_region"][region].update(change)
    if region == "evader" and "x_step" in change:
        doc["players"]["num_e"] = 3
    assert "arena" in str(assert_rejected_at(doc, f"players.respawn_region.{region}"))


@pytest.mark.parametrize("bad", ["cone", "Box", "", 3, None, ["box"], {"kind": "box"}])
def test_bad_obstacle_type_is_rejected(bad: Any) -> None:
    doc = task_document("4p2e1o")
    doc["site"]["obstacles"]["bar"]["type"] = bad
    assert_rejected_at(doc, "site.obstacles.bar.type")


@pytest.mark.parametrize(
    "path",
    [
        ("site", "obstacles", "bar", "x"),
        ("site", "obstacles", "bar", "y"),
        ("players", "respawn_region", "pursuer", "x"),
        ("players", "respawn_region", "evader", "y"),
    ],
)
def test_interval_with_low_above_high_is_rejected(path: Path_) -> None:
    doc = task_document("4p2e1o")
    lo, hi = get(doc, path)
    error = assert_rejected_at(mutate(doc, path, set_to=[hi, lo]), fmt(path))
    assert "low <= high" in str(error)


def test_interval_of_wrong_length_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["site"]["obstacles"]["bar"]["x"] = [1.0, 1.5, 2.0]
    assert_rejected_at(doc, "site.obstacles.bar.x")


def test_proximity_band_with_low_not_below_high_is_rejected() -> None:
    doc = task_document("4p2e1o")
    doc["task"]["reward"]["proximity"]["bands"][1] = [0.3, 0.25, -0.1]
    assert_rejected_at(doc, "task.reward.proximity.bands[1]")


@pytest.mark.parametrize(
    "value", [float("nan"), float("inf"), 10**400, -(10**400)], ids=["nan", "inf", "1e400-int", "-1e400-int"]
)
def test_non_finite_or_overflowing_number_is_rejected(value: float) -> None:
    # JSON "1e999" parses as inf and a 400-digit integer literal as a Python int no float can hold.
    doc = task_document("4p2e1o")
    doc["players"]["velocity_p"] = value
    assert_rejected_at(doc, "players.velocity_p")


def test_invalid_json_file_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "broken.json"
    path.write_text('{"players": {"num_p": 4,}')
    with pytest.raises(ConfigError, match="not valid JSON") as info:
        load_task(path)
    assert str(path) in str(info.value)
    assert info.value.path == "<root>"


def test_json_file_that_is_not_an_object_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "list.json"
    path.write_text("[1, 2, 3]")
    with pytest.raises(ConfigError, match=r"^<root>: must be an object"):
        load_task(path)


def test_malformed_json_file_reports_field_path(tmp_path: Path) -> None:
    doc = task_document("4p2e1o")
    doc["players"]["reception_range"] = -2.0
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ConfigError, match=r"^players\.reception_range: "):
        load_task(path)


@pytest.mark.parametrize("name", ["4p9e9o", "4P2E1O", "", "no/such/file.json"])
def test_unknown_task_name_is_rejected(name: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_task(name)
    for known in TASK_NAMES:
        assert known in str(info.value)


# ------------------------------------------------ every field, exhaustively and at random
# 4p2e3o holds both obstacle kinds, so its document spells out every field of the schema.
FULL_DOC = task_document("4p2e3o")
ALL_PATHS = list(walk(FULL_DOC))
MAPPINGS: list[Path_] = [(), *(p for p in ALL_PATHS if isinstance(get(FULL_DOC, p), dict))]


def _schema_fields(tp: Any, prefix: str = "") -> set[str]:
    """Every field path of the schema (obstacle names and list items made generic)."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return set().union(*(_schema_fields(arg, prefix) for arg in typing.get_args(tp)))
    if typing.get_origin(tp) is dict:
        return _schema_fields(typing.get_args(tp)[1], f"{prefix}.<obstacle>")
    if not dataclasses.is_dataclass(tp):
        return set()
    hints = typing.get_type_hints(tp)
    out = set()
    for f in dataclasses.fields(tp):
        path = f"{prefix}.{f.name}" if prefix else f.name
        out |= {path, *_schema_fields(hints[f.name], path)}
    return out


def test_mutation_generator_covers_every_schema_field() -> None:
    generated = {pattern(p) for p in ALL_PATHS}
    generated = {p for p in generated if not p.endswith("[]")} - {"site.obstacles.<obstacle>"}
    assert generated == _schema_fields(TaskConfig)


@pytest.mark.parametrize("path", ALL_PATHS, ids=fmt)
def test_deleting_any_field_loads_with_default_or_names_it(path: Path_) -> None:
    check_deletion(FULL_DOC, path)


@pytest.mark.parametrize("path", ALL_PATHS, ids=fmt)
def test_wrong_type_in_any_field_is_named(path: Path_) -> None:
    for value in wrong_values(path, get(FULL_DOC, path)):
        check_wrong_type(FULL_DOC, path, value)


@pytest.mark.parametrize("mapping", MAPPINGS, ids=lambda p: fmt(p) or "<root>")
def test_unknown_key_in_any_object_is_named(mapping: Path_) -> None:
    check_unknown_key(FULL_DOC, mapping, "unexpected", 1)


DOCS = {name: task_document(name) for name in TASK_NAMES}


@st.composite
def malformations(draw: st.DrawFn) -> tuple[str, dict[str, Any], str, Path_, Any]:
    doc = DOCS[draw(st.sampled_from(TASK_NAMES))]
    path = draw(st.sampled_from(list(walk(doc))))
    kind = draw(st.sampled_from(["delete", "retype", "insert"]))
    if kind == "delete":
        return kind, doc, "", path, None
    if kind == "retype":
        return kind, doc, "", path, draw(wrong_value_strategy(path, get(doc, path)))
    # insert beside the chosen field: into the nearest enclosing object
    mapping = path[:-1]
    while not isinstance(get(doc, mapping), dict):
        mapping = mapping[:-1]
    taken = get(doc, mapping)
    key = draw(st.text(min_size=1, max_size=8).filter(lambda k: k not in taken))
    value = draw(st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=5)))
    return kind, doc, key, mapping, value


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(malformations())
def test_random_malformation_is_rejected_at_its_path(case: tuple[str, dict[str, Any], str, Path_, Any]) -> None:
    kind, doc, key, path, value = case
    if kind == "delete":
        check_deletion(doc, path)
    elif kind == "retype":
        check_wrong_type(doc, path, value)
    else:
        check_unknown_key(doc, path, key, value)


# Integer fields stay small: a count of 10**9 evaders is valid but slow to validate.
FLOAT_VALUES = st.one_of(
    st.integers(),
    st.integers(min_value=10**300, max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
)
INT_VALUES = st.one_of(st.integers(min_value=-1000, max_value=1000), st.floats(allow_nan=True, allow_infinity=True))
NUMERIC_PATHS = {
    name: [p for p in walk(doc) if is_int(get(doc, p)) or isinstance(get(doc, p), float)] for name, doc in DOCS.items()
}


# The rule each numeric field obeys on its own (SPEC section 7), by its generic path; a box's or spawn region's
# x and y items are checked as their [low, high] pair, named by the pair's path.
POSITIVE = {
    "players.reception_range",
    "players.velocity_p",
    "players.velocity_e",
    "site.boundary.width",
    "site.boundary.height",
    "site.obstacles.<obstacle>.radius",
    "task.capture_range",
    "task.safe_radius",
    "task.collision_distance",
    "task.reward.approach_scale",
}
NON_NEGATIVE = {"players.num_unctrl", "players.respawn_region.pursuer.x_step", "players.respawn_region.evader.x_step"}
BETWEEN = {
    "players.num_p": (2, 64),
    "players.num_e": (1, 64),
    "players.num_ctrl": (1, 64),
    "task.task_horizon": (1, 100_000),
    "task.fps": (1, 1000),
}
INTERVALS = {
    "players.respawn_region.pursuer.x[]",
    "players.respawn_region.pursuer.y[]",
    "players.respawn_region.evader.x[]",
    "players.respawn_region.evader.y[]",
    "site.obstacles.<obstacle>.x[]",
    "site.obstacles.<obstacle>.y[]",
}


def field_rule_broken(doc: dict[str, Any], path: Path_, value: Any) -> tuple[str, str] | None:
    """(path named, words of the message) when ``value`` at ``path`` breaks its field's own rule, else None."""
    if is_float_field(path, get(doc, path)):
        try:
            number = float(value)
        except OverflowError:
            return fmt(path), "must be finite"
        if not math.isfinite(number):
            return fmt(path), "must be finite"
    elif not is_int(value):
        return fmt(path), "must be an integer"
    generic = pattern(path)
    if generic in POSITIVE and not value > 0:
        return fmt(path), "must be > 0"
    if generic in NON_NEGATIVE and not value >= 0:
        return fmt(path), "must be >= 0"
    if generic in BETWEEN and not BETWEEN[generic][0] <= value <= BETWEEN[generic][1]:
        return fmt(path), "must be between"
    if generic in INTERVALS:
        low, high = (value, get(doc, path[:-1])[1]) if path[-1] == 0 else (get(doc, path[:-1])[0], value)
        if not low <= high:
            return fmt(path[:-1]), "with low <= high"
    return None


def cross_field_rules_broken(doc: dict[str, Any]) -> set[str]:
    """The paths of the rules between fields that ``doc`` (every field of its own valid) breaks (SPEC section 7)."""
    players, task = doc["players"], doc["task"]
    width, height = doc["site"]["boundary"]["width"], doc["site"]["boundary"]["height"]
    broken = set()
    if players["num_ctrl"] + players["num_unctrl"] != players["num_p"]:
        broken.add("players.num_ctrl")
    for key in ("capture_range", "collision_distance"):
        if task[key] >= min(width, height):
            broken.add(f"task.{key}")
    if task["safe_radius"] >= min(width, height) / 2:
        broken.add("task.safe_radius")
    for name, ob in doc["site"]["obstacles"].items():
        if ob["type"] == "box":
            inside = 0 <= ob["x"][0] < ob["x"][1] <= width and 0 <= ob["y"][0] < ob["y"][1] <= height
        else:
            (cx, cy), r = ob["center"], ob["radius"]
            inside = r <= cx <= width - r and r <= cy <= height - r
        if not inside:
            broken.add(f"site.obstacles.{name}")
    margin = task["safe_radius"]
    for kind, count in (("pursuer", players["num_p"]), ("evader", players["num_e"])):
        region = players["respawn_region"][kind]
        for i in range(count):
            x0, x1 = (x + region["x_step"] * i for x in region["x"])
            (y0, y1) = region["y"]
            clear_of_walls = margin <= x0 and x1 <= width - margin and margin <= y0 and y1 <= height - margin
            if not clear_of_walls or any(
                _near(ob, (x0, x1), (y0, y1), margin) for ob in doc["site"]["obstacles"].values()
            ):
                broken.add(f"players.respawn_region.{kind}")
    for i, (low, high, _) in enumerate(task["reward"]["proximity"]["bands"]):
        if not 0 <= low < high:
            broken.add(f"task.reward.proximity.bands[{i}]")
    return broken


def _near(ob: dict[str, Any], xs: tuple[float, float], ys: tuple[float, float], margin: float) -> bool:
    """Whether the rectangle xs x ys comes closer than ``margin`` to the obstacle (touching at margin is clear)."""
    if ob["type"] == "box":
        (bx0, bx1), (by0, by1) = ob["x"], ob["y"]  # the rectangle meets the box grown by the margin
        return xs[0] < bx1 + margin and xs[1] > bx0 - margin and ys[0] < by1 + margin and ys[1] > by0 - margin
    (cx, cy), r = ob["center"], ob["radius"]
    nearest = (min(max(cx, xs[0]), xs[1]), min(max(cy, ys[0]), ys[1]))
    return math.dist((cx, cy), nearest) < r + margin


@pytest.mark.parametrize("name", TASK_NAMES)
def test_the_paper_tasks_break_no_rule_of_the_oracle(name: str) -> None:
    """The oracle below judges the shipped tasks valid, as load_task does: it is not rejecting everything."""
    assert cross_field_rules_broken(DOCS[name]) == set()
    assert all(field_rule_broken(DOCS[name], p, get(DOCS[name], p)) is None for p in NUMERIC_PATHS[name])


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_any_number_in_any_numeric_field_loads_exactly_when_every_rule_holds(data: st.DataObject) -> None:
    """A number put into any numeric field: rejected at that field when it breaks the field's own rule (type,
    finiteness, sign, range, low <= high), else rejected at a rule between fields it breaks, else loaded with
    that number in that field, the rest of the task unchanged and every number finite."""
    name = data.draw(st.sampled_from(TASK_NAMES))
    path = data.draw(st.sampled_from(NUMERIC_PATHS[name]))
    value = data.draw(FLOAT_VALUES if is_float_field(path, get(DOCS[name], path)) else INT_VALUES)
    mutated = mutate(DOCS[name], path, set_to=value)
    own = field_rule_broken(DOCS[name], path, value)
    # the document as load_task reads it: a number in a float field as a float
    parsed = mutate(
        DOCS[name], path, set_to=float(value) if own is None and is_float_field(path, get(DOCS[name], path)) else value
    )
    between = cross_field_rules_broken(parsed) if own is None else set()
    if own is not None:
        error = assert_rejected_at(mutated, own[0])
        assert own[1] in str(error), error
    elif between:
        with pytest.raises(ConfigError) as info:
            load_task(mutated)
        assert info.value.path in between, (info.value, between)
    else:
        cfg = load_task(mutated)
        assert cfg.to_dict() == parsed  # the number kept (an integer in a float field as that float)
        assert all(math.isfinite(v) for v in _numbers(cfg.to_dict()))


def _numbers(node: Any) -> Iterator[float]:
    if isinstance(node, dict):
        for v in node.values():
            yield from _numbers(v)
    elif isinstance(node, list):
        for v in node:
            yield from _numbers(v)
    elif isinstance(node, int | float) and not isinstance(node, bool):
        yield float(node)


# ------------------------------------------------- a run saves every PPO value it trains with
def _service_doc(**ppo: Any) -> dict[str, Any]:
    return {"name": "ppo_t", "algorithm": "sp", "task": "4p2e1o", "sp": {}, "ppo": dict(ppo)}


def _saved(tmp_path: Path, config: dict[str, Any]) -> Path:
    run_dir = tmp_path / "ppo_t"
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(config))
    return run_dir


def test_a_run_config_holds_every_ppo_value_so_a_changed_default_cannot_change_a_resumed_run(tmp_path: Path) -> None:
    from atdrone.learn import ppo
    from atdrone.learn.trainer import load_train_config
    from atdrone.rundir import RunError, check_resume
    from atdrone.service.driver import RESUME_MAY_CHANGE
    from atdrone.service.experiment import load_experiment

    cfg = load_experiment(_service_doc(hidden=32))
    assert cfg.ppo == {**dataclasses.asdict(ppo.PRESETS["default"]), "hidden": 32}  # every field, as run with
    train = load_train_config({"name": "t", "task": "4p2e1o", "preset": "paper", "ppo": {"lr": 1e-3}})
    assert train.ppo == {**dataclasses.asdict(ppo.PRESETS["paper"]), "lr": 1e-3}
    run_dir = _saved(tmp_path, cfg.to_dict())
    check_resume(run_dir, cfg.to_dict(), RESUME_MAY_CHANGE, ppo.saved_ppo_document)

    # a run begun when the default had 2 epochs (before issue 26) resumes only with the values it trained with
    then = _saved(tmp_path / "then", load_experiment(_service_doc(hidden=32, epochs=2)).to_dict())
    with pytest.raises(RunError, match=r"ppo\.epochs: 2 -> 4"):
        check_resume(then, load_experiment(_service_doc(hidden=32)).to_dict(), RESUME_MAY_CHANGE)
    pinned = load_experiment(_service_doc(hidden=32, epochs=2)).to_dict()
    check_resume(then, pinned, RESUME_MAY_CHANGE, ppo.saved_ppo_document)


def test_a_run_saved_with_ppo_overrides_only_resumes_with_the_values_of_its_time(tmp_path: Path) -> None:
    """config.json as runs wrote it before they saved every value: the overrides alone. Such a run trained
    with the presets of then (OVERRIDES_ERA_PRESETS), and a resume compares with those, not with today's."""
    from atdrone.learn import ppo
    from atdrone.rundir import RunError, check_resume
    from atdrone.service.driver import RESUME_MAY_CHANGE
    from atdrone.service.experiment import load_experiment

    # only the default's epochs and lr moved since (2 -> 4 and 3e-4 -> 1e-3, issue 26)
    era = {"default": dataclasses.replace(ppo.PRESETS["default"], epochs=2, lr=3e-4), "paper": ppo.PRESETS["paper"]}
    assert era == ppo.OVERRIDES_ERA_PRESETS
    then = load_experiment(_service_doc(hidden=32, epochs=2, lr=3e-4)).to_dict()
    run_dir = _saved(tmp_path, {**then, "ppo": {"hidden": 32}})
    with pytest.raises(RunError, match=r"ppo\.epochs: '<unset>' -> 2"):  # the text alone is not what it ran
        check_resume(run_dir, then, RESUME_MAY_CHANGE)
    check_resume(run_dir, then, RESUME_MAY_CHANGE, ppo.saved_ppo_document)
    with pytest.raises(RunError, match=r"ppo\.hidden: 32 -> 128"):  # its own override still counts
        check_resume(
            run_dir,
            load_experiment(_service_doc(epochs=2, lr=3e-4)).to_dict(),
            RESUME_MAY_CHANGE,
            ppo.saved_ppo_document,
        )
    today = load_experiment(_service_doc(hidden=32)).to_dict()
    with pytest.raises(RunError, match=r"ppo\.epochs: 2 -> 4.*ppo\.lr: 0\.0003 -> 0\.001"):  # today's defaults
        check_resume(run_dir, today, RESUME_MAY_CHANGE, ppo.saved_ppo_document)


COMMITTED_DRONES = sorted((CONFIG_DIR / "zoos" / "checkpoints").glob("*/*.pt")) + sorted(
    (CONFIG_DIR / "pools" / "checkpoints").glob("*/*.pt")
)


@pytest.mark.parametrize("checkpoint", COMMITTED_DRONES, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_a_committed_drones_recipe_trains_with_the_ppo_values_in_its_header(checkpoint: Path) -> None:
    """configs/train/<name>.json, the recipe its README names, loads with every PPO value the drone was trained
    with (its header): a later change of a PPO default cannot change what the recipe trains."""
    from atdrone.learn.trainer import load_train_config
    from atdrone.models.checkpoint import read_header

    header = read_header(checkpoint)
    recipe = CONFIG_DIR / "train" / f"{header['config']['name']}.json"
    ppo = load_train_config(recipe).ppo
    assert {k: ppo[k] for k in header["ppo"]} == header["ppo"]
