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
    from atdrone.policies.rules import GreedyPolicy
    from atdrone.policies.zoo import load_zoo
    from atdrone.teams.replay import showcase

    zoo = load_zoo("zoo2")
    policy = GreedyPolicy()
    policy.name = "member-x"
    frames, summary = showcase("4p2e1o", policy, zoo, seed=0, tries=3, frame_every=7)
    steps, k = summary["steps"], 7
    assert summary["outcome"] in ("captured", "collision", "timeout")  # played to its end, not cut
    assert len(frames) == 1 + steps // k + (1 if steps % k else 0)  # every 7th step, the first and the last
    assert set(summary["team"]["partners"]) <= set(zoo.names) and len(summary["team"]["partners"]) == 2
    partners = ", ".join(summary["team"]["partners"])
    assert summary["caption"].startswith(f"member-x + {partners}: {summary['outcome']} in {steps} steps")
    if summary["outcome"] != "captured":  # no seed of the three captured: the longest episode was kept
        lengths = [showcase("4p2e1o", policy, zoo, seed=s, tries=1, frame_every=10**9)[1]["steps"] for s in range(3)]
        assert steps == max(lengths)
