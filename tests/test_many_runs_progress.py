"""A population run's progress lines: one when something changed, never the same line again."""

from __future__ import annotations

from typing import Any

import pytest

from atdrone.service import driver


class _Remote:
    def __init__(self, call: Any) -> None:
        self.remote = call


class _Coordinator:
    """What ``_await_generation`` asks a coordinator: its generation (done after ``polls``) and its progress."""

    def __init__(self, lines: list[str]) -> None:
        self.lines = lines
        self.run_generation = _Remote(lambda: "generation")
        self.progress = _Remote(lambda: self.lines.pop(0) if len(self.lines) > 1 else self.lines[0])


def test_progress_prints_a_line_only_when_it_changed(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import ray

    polls = iter(range(12))
    clock = iter(range(0, 1000, 20))  # 20 s between polls: past the 10 s pace every time
    monkeypatch.setattr(ray, "wait", lambda refs, timeout: (refs if next(polls) == 11 else [], []))
    monkeypatch.setattr(ray, "get", lambda ref: "report" if ref == "generation" else ref)
    monkeypatch.setattr(driver.time, "monotonic", lambda: float(next(clock)))
    seen = ["train: learner 1, update 1/6"] * 4 + ["train: learner 1, update 2/6"] * 3 + ["evaluate: 3 matches"] * 4
    assert driver._await_generation(_Coordinator(seen), "run", 0, progress=True) == "report"
    printed = capsys.readouterr().out.splitlines()
    assert printed == [
        "[run] generation 0: train: learner 1, update 1/6",
        "[run] generation 0: train: learner 1, update 2/6",
        "[run] generation 0: evaluate: 3 matches",
    ]
