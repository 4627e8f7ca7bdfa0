"""Rendering: frames, GIF/PNG files, the ``atdrone render`` command and lazy imports."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from atdrone.cli import main
from atdrone.envs.core import BatchedPursuit
from atdrone.envs.render import render_frame, save_gif, save_png
from atdrone.policies.rules import chase_nearest
from atdrone.teams.replay import record_episode


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
    before = core.state.copy()
    rng_before = core.rng.bit_generator.state
    render_frame(core, 0)
    for key, value in before.__dict__.items():
        np.testing.assert_array_equal(getattr(core.state, key), value, err_msg=key)
    assert core.rng.bit_generator.state == rng_before


def test_render_frame_draws_a_given_state_not_the_current_one():
    core = BatchedPursuit("4p2e1o", num_envs=1, seed=0)
    core.reset()
    moved = core.state.copy()
    moved.pos[0, :, 0] = 3.6 - moved.pos[0, :, 0]  # mirror every drone
    assert not np.array_equal(render_frame(core, 0, state=moved), render_frame(core, 0))


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
    assert main(["demo", "--out-dir", str(tmp_path), "--max-steps", "3", "--frame-every", "3"]) == 0
    expected = [f"{t}.gif" for t in ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")]
    assert sorted(p.name for p in tmp_path.glob("*.gif")) == expected
    out = capsys.readouterr().out
    assert "outcome" in out and "4p3e5o" in out


def test_importing_the_envs_does_not_import_matplotlib():
    code = "import sys, atdrone.envs, atdrone.cli; assert 'matplotlib' not in sys.modules, 'matplotlib imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
