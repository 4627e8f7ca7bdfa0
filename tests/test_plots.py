"""Pictures a person can read: labelled axes and colour bars, titles inside the figure, arrows that show."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from matplotlib.patches import FancyArrowPatch

from atdrone.population.plots import crossplay_figure, crossplay_heatmap, hypergraph_figure


def _table(n: int) -> pd.DataFrame:
    ids = [f"hola-g{i // 2}-{i % 2}" for i in range(n)]
    values = np.random.default_rng(n).uniform(0, 100, (n, n))
    values[0, -1] = np.nan
    return pd.DataFrame(values, index=pd.Index(ids, name="member"), columns=pd.Index(ids, name="partner"))


@pytest.mark.parametrize("n", [2, 8, 30])
def test_the_crossplay_heatmap_is_labelled_and_its_title_fits(n):
    title = "hola_quick cross-play SUC of every member with every partner, generation 12 of a long experiment run"
    fig = crossplay_figure(_table(n), title=title)
    ax, bar_ax = fig.axes
    assert (ax.get_xlabel(), ax.get_ylabel()) == ("partner", "member")
    assert bar_ax.get_ylabel() == "SUC (%)"
    assert [t.get_text() for t in ax.get_xticklabels()] == list(_table(n).columns)
    fig.canvas.draw()
    box, frame = ax.title.get_window_extent(), fig.bbox
    assert frame.x0 <= box.x0 and box.x1 <= frame.x1, (box, frame)  # the title fits the figure's width


def test_the_crossplay_heatmap_is_written(tmp_path):
    path = crossplay_heatmap(_table(3), tmp_path / "c.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_crossplay_colour_scale_spans_the_values_present():
    values = np.array([[2.0, 7.0], [np.nan, 4.5]])
    table = pd.DataFrame(values, index=["a", "b"], columns=["a", "b"])
    image = crossplay_figure(table).axes[0].images[0]
    assert image.norm.vmin == 2.0 and image.norm.vmax == 7.0  # not 0-100: 2 and 7 are the scale's two ends
    assert image.norm(4.5) == pytest.approx(0.5)
    flat = crossplay_figure(pd.DataFrame([[5.0]], index=["a"], columns=["a"])).axes[0].images[0]
    assert (flat.norm.vmin, flat.norm.vmax) == (4.5, 5.5)


def test_the_hypergraph_shows_each_preference_as_an_arrow_and_a_key_for_eta():
    weights = {"a|b|l": 40.0, "a|c|l": 30.0, "b|c|l": 20.0}
    preference = {"a": ["b", "l"], "b": ["a", "l"], "c": ["a", "l"]}
    eta = {"a": 0.5, "b": 0.25, "c": 0.0}
    fig = hypergraph_figure(weights, preference, eta)
    ax, bar_ax = fig.axes
    arrows = [p for p in ax.patches if isinstance(p, FancyArrowPatch)]
    assert len(arrows) == sum(len(set(team) - {m}) for m, team in preference.items()) == 6
    assert all(a.get_arrowstyle().__class__.__name__ == "CurveFilledB" for a in arrows)  # "-|>": a visible head
    assert bar_ax.get_ylabel().startswith("eta")
    labels = {t.get_text() for t in ax.texts}
    assert {"a\neta 0.50", "c\neta 0.00", "l\n(no eta yet)"} <= labels
    # with rho and the generation: each member's share of the partner draws, and which generation it is
    fig = hypergraph_figure(weights, preference, eta, rho={"a": 0.2, "b": 0.3, "c": 0.5}, generation=3)
    ax = fig.axes[0]
    assert "c\neta 0.00\nrho 0.50" in {t.get_text() for t in ax.texts}
    assert ax.get_title().startswith("generation 3: preference hypergraph")


def test_the_showcase_is_a_whole_episode_with_zoo_partners_and_a_caption():
    """The showcase keeps the usual outcome's lower-median episode of its seeds, and reports it as played:
    replaying the kept seed alone gives the same outcome, length, return and team, and the outcome is the one
    the final state shows (every evader caught, a collision, or the horizon reached)."""
    from atdrone.policies.rules import GreedyPolicy
    from atdrone.policies.zoo import load_zoo
    from atdrone.teams.replay import play_episode, showcase

    zoo = load_zoo("zoo2", "4p2e1o")
    policy = GreedyPolicy()
    policy.name = "member-x"
    frames, summary = showcase("4p2e1o", policy, zoo, seed=0, tries=3, frame_every=7)
    # the three seeds played one by one: which outcome most ended with, and that outcome's lower-median length
    played = [play_episode("4p2e1o", s, policy, partners=zoo) for s in range(3)]
    outcomes = [e.summary["outcome"] for e in played]
    usual = max(outcomes, key=outcomes.count)  # a tie goes to the earlier seed's outcome
    alike = sorted((e for e in played if e.summary["outcome"] == usual), key=lambda e: e.summary["steps"])
    kept = alike[(len(alike) - 1) // 2]
    assert {k: summary[k] for k in kept.summary} == kept.summary  # seed, steps, outcome, return, captured, team
    assert summary["typical"] == f"{outcomes.count(usual)} of 3 seeds ended {usual}"
    final, horizon = kept.states[-1], kept.core.cfg.task.task_horizon
    shown = (
        "captured"
        if final.captured[0].all()
        else "collision"
        if final.ep_collided[0]
        else "timeout"
        if final.t[0] == horizon
        else "running"
    )
    assert summary["outcome"] == shown != "running"  # played to its end, not cut
    assert summary["captured"] == int(final.captured[0].sum()) and summary["steps"] == int(final.t[0])
    steps, k = summary["steps"], 7
    assert len(frames) == 1 + steps // k + (1 if steps % k else 0)  # every 7th step, the first and the last
    assert set(summary["team"]["partners"]) <= set(zoo.names) and len(summary["team"]["partners"]) == 2
    partners = ", ".join(summary["team"]["partners"])
    assert summary["caption"].startswith(f"member-x + {partners}: {summary['outcome']} in {steps} steps")
