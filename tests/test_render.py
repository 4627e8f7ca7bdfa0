"""Rendering: frames, GIF/PNG files, the ``atdrone render`` command, lazy imports, the best member's
captioned GIF and the cross-play heatmap of a large population."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from atdrone.cli import main
from atdrone.config import load_task
from atdrone.envs.core import BatchedPursuit
from atdrone.envs.render import COLLISION_COLOR, FrameRenderer, render_frame, save_gif, save_png, two_lines
from atdrone.policies.rules import GreedyPolicy, chase_nearest
from atdrone.policies.zoo import load_zoo
from atdrone.population.plots import crossplay_figure
from atdrone.teams.match import Match
from atdrone.teams.replay import (
    frame_steps,
    play_episode,
    record_episode,
    representative_episode,
    showcase,
    showcase_gif,
)


def test_render_frame_is_an_rgb_uint8_image_of_plausible_size():
    core = BatchedPursuit("4p2e3o", num_envs=2, seed=0)
    core.reset()
    frame = render_frame(core, 1, title="test")
    assert frame.dtype == np.uint8
    assert frame.ndim == 3 and frame.shape[2] == 3
    h, w, _ = frame.shape
    assert 200 <= w <= 2000 and 200 <= h <= 2000
    assert h > w  # the arena is 3.6 m wide and 5 m tall
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 10  # not blank


def test_rendering_leaves_the_simulator_unchanged():
    core = BatchedPursuit("4p2e5o", num_envs=1, seed=3)
    obs = core.reset()
    for _ in range(5):
        obs, *_ = core.step(chase_nearest(obs, core.num_e))
    before, next_episode = core.state.copy(), core.next_episode
    render_frame(core, 0)
    for key, value in before.__dict__.items():
        np.testing.assert_array_equal(getattr(core.state, key), value, err_msg=key)
    assert core.next_episode == next_episode  # no episode started (its draws come from its key)


def test_render_frame_draws_a_given_state_not_the_current_one():
    core = BatchedPursuit("4p2e1o", num_envs=1, seed=0)
    core.reset()
    moved = core.state.copy()
    moved.pos[0, :, 0] = 3.6 - moved.pos[0, :, 0]  # mirror every drone
    assert not np.array_equal(render_frame(core, 0, state=moved), render_frame(core, 0))


def _orange_pixels(frame: np.ndarray) -> int:
    rgb = np.array([int(COLLISION_COLOR[k : k + 2], 16) for k in (1, 3, 5)])
    return int((np.abs(frame.astype(int) - rgb).sum(-1) < 40).sum())


def test_a_collision_is_marked_where_the_simulator_judges_one():
    core = BatchedPursuit("4p2e1o", num_envs=1, seed=0)
    core.reset()
    renderer = FrameRenderer(core, 0)
    clear = _orange_pixels(renderer.draw())  # the legend's key only
    apart = core.state.copy()
    apart.pos[0, 1] = apart.pos[0, 0] + [core.cfg.task.collision_distance + 0.01, 0.0]  # just outside the rule
    assert _orange_pixels(renderer.draw(apart)) == clear
    hit = apart.copy()
    hit.pos[0, 1] = hit.pos[0, 0] + [core.cfg.task.collision_distance - 0.01, 0.0]
    assert _orange_pixels(renderer.draw(hit)) > clear + 200  # a star behind each of the pair and a line
    wall = core.state.copy()
    wall.pos[0, 3] = [1.75, 2.45 - core.cfg.task.safe_radius / 2]  # against the bar
    assert _orange_pixels(renderer.draw(wall)) > clear + 100


def test_record_episode_stops_at_max_steps_and_draws_every_kth_step():
    frames, summary = record_episode("4p2e1o", seed=1, max_steps=9, frame_every=4)
    assert summary["task"] == "4p2e1o" and summary["seed"] == 1
    assert summary["outcome"] == "running" and summary["steps"] == 9
    assert len(frames) == 4  # steps 0, 4, 8 and the last one, 9
    assert {"return", "captured", "num_e"} <= set(summary)


def test_record_episode_runs_to_the_end_and_shows_the_final_state():
    # flying straight ahead, pursuer 2 (spawned at x 1.4-2.4) always hits the bar at y 2.45
    straight = lambda obs, core: np.zeros((1, core.num_p))
    frames, summary = record_episode("4p2e1o", seed=0, policy=straight, frame_every=10)
    assert summary["outcome"] == "collision"
    steps = summary["steps"]
    assert 0 < steps < 80
    assert len(frames) == steps // 10 + 1 + (steps % 10 != 0)  # step 0, every 10th, the final one


def test_save_png_and_gif_write_readable_images(tmp_path):
    frame = np.zeros((40, 30, 3), dtype=np.uint8)
    frame[10:20, 5:15] = (200, 30, 30)
    save_png(frame, tmp_path / "a.png")
    with Image.open(tmp_path / "a.png") as im:
        assert im.size == (30, 40)
        np.testing.assert_array_equal(np.asarray(im.convert("RGB")), frame)
    frames = [np.roll(frame, k, axis=1) for k in range(3)]
    save_gif(frames, tmp_path / "sub" / "a.gif", fps=5)
    with Image.open(tmp_path / "sub" / "a.gif") as im:
        assert im.n_frames == 3
        assert im.info["duration"] == 200
    assert not list(tmp_path.rglob("*.tmp"))  # no temp files left behind


def test_cli_render_writes_a_multiframe_gif_and_a_png(tmp_path, capsys):
    gif, png = tmp_path / "run.gif", tmp_path / "frame.png"
    code = main(
        ["render", "--task", "4p2e5o", "--out", str(gif), "--png", str(png), "--max-steps", "12", "--frame-every", "3"]
    )
    assert code == 0
    with Image.open(gif) as im:
        assert im.n_frames >= 3
    with Image.open(png) as im:
        assert im.format == "PNG" and im.mode == "RGB"
    out = capsys.readouterr().out
    assert str(gif) in out and "4p2e5o" in out


@pytest.mark.parametrize("task", ["no-such-task", "missing/file.json"])
def test_cli_render_rejects_a_bad_task_with_exit_code_2(task, tmp_path, capsys):
    assert main(["render", "--task", task, "--out", str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert task in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.gif").exists()


def test_cli_render_names_the_bad_field_of_a_task_file(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"players": {"num_p": 4}}')
    assert main(["render", "--task", str(bad)]) == 2
    assert "players." in capsys.readouterr().err


def test_cli_demo_renders_every_task(tmp_path, capsys):
    assert main(["gallery", "--out-dir", str(tmp_path), "--max-steps", "3", "--frame-every", "3"]) == 0
    expected = [f"{t}.gif" for t in ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")]
    assert sorted(p.name for p in tmp_path.glob("*.gif")) == expected
    out = capsys.readouterr().out
    assert "outcome" in out and "4p3e5o" in out


def test_importing_the_envs_does_not_import_matplotlib():
    code = "import sys, atdrone.envs, atdrone.cli; assert 'matplotlib' not in sys.modules, 'matplotlib imported'"
    subprocess.run([sys.executable, "-c", code], check=True)


# ------------------------------------------------------------------ captions and the best member's GIF
LONG_CAPTION = "hola_quick-g12-3 + sp_high, sp_low: collision in 1000 steps (1/2 caught), seed 7"


def test_a_long_caption_wraps_onto_two_readable_lines_above_the_status_line():
    renderer = FrameRenderer(BatchedPursuit("4p2e1o", num_envs=1, seed=0))
    renderer.core.reset()
    renderer.draw(title=LONG_CAPTION)
    figure, title, status = renderer.figure.bbox, renderer.title, renderer.status
    assert title.get_text() == two_lines(LONG_CAPTION) and title.get_text().replace("\n", " ") == LONG_CAPTION
    assert title.get_fontsize() >= 8  # not shrunk to a smudge
    box, line = title.get_window_extent(), status.get_window_extent()
    assert figure.x0 <= box.x0 and box.x1 <= figure.x1 and box.y1 <= figure.y1, (box, figure)
    assert line.y1 <= box.y0 and renderer.ax.get_window_extent().y1 <= line.y0  # title, status, arena


def test_frame_steps_show_the_whole_episode():
    assert frame_steps(8, 4) == [0, 4, 8]
    assert frame_steps(9, 4) == [0, 4, 8, 9]
    assert frame_steps(0, 4) == [0]
    assert all(len(frame_steps(n, k)) == math.ceil(n / k) + 1 for n in range(1, 30) for k in range(1, 9))
    with pytest.raises(ValueError, match="frame_every"):
        frame_steps(5, 0)


def test_the_representative_episode_has_the_usual_outcome_and_a_median_length():
    zoo = load_zoo("zoo2", "4p2e1o")
    played = [play_episode("4p2e1o", s, GreedyPolicy(), partners=zoo).summary for s in range(8, 13)]
    # greedy learners with the Zoo 2 drones, seeds 8-12: one collision, then four captures
    assert [(p["outcome"], p["steps"]) for p in played] == [
        ("collision", 37),
        ("captured", 388),
        ("captured", 192),
        ("captured", 176),
        ("captured", 242),
    ]
    chosen = representative_episode("4p2e1o", GreedyPolicy(), zoo, seed=8, tries=5).summary
    # captured is the usual outcome (4 of 5); of 176, 192, 242, 388 steps the lower median is seed 10's 192,
    # not the first capture (seed 9) nor the quickest (seed 11)
    assert (chosen["seed"], chosen["steps"]) == (10, 192)
    assert chosen["typical"] == "4 of 5 seeds ended captured"
    # a tie goes to the earlier seed's outcome: with seeds 8 and 9 the collision is shown, not the capture
    tie = representative_episode("4p2e1o", GreedyPolicy(), zoo, seed=8, tries=2).summary
    assert (tie["seed"], tie["outcome"], tie["typical"]) == (8, "collision", "1 of 2 seeds ended collision")


def test_showcase_gif_plays_the_member_with_zoo_partners_and_captions_the_whole_episode(tmp_path):
    policy = GreedyPolicy()
    policy.name = "member-x"
    shown = showcase_gif("4p2e1o", policy, "zoo2", seed=0, out=tmp_path / "best.gif", max_tries=2, frame_every=7)
    assert set(shown) == {"member", "partners", "seed", "outcome", "steps", "captured", "num_e", "caption"} | {
        "frames",
        "path",
    }
    steps, horizon = shown["steps"], load_task("4p2e1o").task.task_horizon
    assert shown["outcome"] in ("captured", "collision") or (shown["outcome"] == "timeout" and steps == horizon)
    assert shown["frames"] == math.ceil(steps / 7) + 1  # step 0, every 7th and the last: the whole episode
    with Image.open(shown["path"]) as im:
        assert im.n_frames == shown["frames"] and im.info["duration"] == 100
    # the partners are the zoo's, and the very ones that played (drawn at the episode's reset)
    match = Match(BatchedPursuit("4p2e1o", num_envs=1, seed=shown["seed"]), load_zoo("zoo2"), seed=shown["seed"])
    match.reset(seed=shown["seed"])
    assert shown["partners"] == match.team()["partners"][0].tolist()
    assert set(shown["partners"]) <= {"sp_high", "sp_low"} and len(shown["partners"]) == 2
    assert shown["member"] == "member-x"
    assert shown["caption"] == (
        f"member-x + {', '.join(shown['partners'])}: {shown['outcome']} in {steps} steps "
        f"({shown['captured']}/{shown['num_e']} caught), seed {shown['seed']}; "
        f"{2 if shown['seed'] == 1 else 1} of 2 seeds ended {shown['outcome']}"
    )
    assert not list(tmp_path.glob("*.tmp"))


def test_the_showcase_draws_the_episode_its_caption_describes():
    # a policy that never plays the same episode twice: what is drawn must be what was picked
    rng = np.random.default_rng(0)

    def jitter(obs: np.ndarray, core: BatchedPursuit) -> np.ndarray:
        return rng.uniform(-1, 1, size=(1, 2))

    frames, summary = showcase("4p2e1o", jitter, load_zoo("zoo1"), seed=0, tries=3, frame_every=3)
    assert summary["caption"].startswith(f"jitter + greedy, greedy: {summary['outcome']} in {summary['steps']} steps")
    assert len(frames) == math.ceil(summary["steps"] / 3) + 1


def test_showcase_without_a_zoo_plays_the_member_alone():
    frames, summary = showcase("4p2e1o", GreedyPolicy(), None, seed=0, tries=1, frame_every=10**6)
    assert "team" not in summary and summary["caption"].startswith("greedy alone: ")
    assert len(frames) == 2


# ------------------------------------------------------------------ the cross-play heatmap, large
def test_the_crossplay_heatmap_of_30_members_keeps_9pt_labels_on_a_screen_sized_figure():
    ids = [f"hola_quick-g{i // 2}-{i % 2}" for i in range(30)]
    values = np.random.default_rng(0).uniform(0, 100, (30, 30))
    fig = crossplay_figure(
        pd.DataFrame(values, index=ids, columns=ids), title="hola_quick cross-play SUC, generation 14"
    )
    assert fig.get_figwidth() <= 14 and fig.get_figheight() <= 14  # about 1400 px: no shrinking to fit a screen
    ax = fig.axes[0]
    labels = ax.get_xticklabels() + ax.get_yticklabels()
    assert len(labels) == 60 and all(t.get_fontsize() >= 9 for t in labels)
    fig.canvas.draw()
    rows = [t.get_window_extent() for t in ax.get_yticklabels()]
    assert all(a.y1 <= b.y0 + 0.5 or b.y1 <= a.y0 + 0.5 for a, b in itertools.pairwise(rows))  # no overlap
    assert all(fig.bbox.x0 <= b.x0 and b.x1 <= fig.bbox.x1 for b in (t.get_window_extent() for t in labels))
    numbers = [t for t in ax.texts if t.get_text().isdigit()]
    assert len(numbers) == 900 and min(t.get_fontsize() for t in numbers) >= 6  # every cell's value, legible
