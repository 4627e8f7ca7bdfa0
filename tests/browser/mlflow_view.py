"""Check in a headless Chromium that an atdrone experiment opens in MLflow's model-training view, on atdrone's
view: the population's SUC numbers as columns of the runs table, and charts without empty sections.

    .venv/bin/python tests/browser/mlflow_view.py [--screenshot docs/img/mlflow-runs.png] [--chromium PATH]

It logs a small population-shaped run through atdrone's tracker (a parent run with per-generation curves and
the numbers :func:`atdrone.tracking.population_columns` names, a nested generation run with ``budget/`` and
``pop/`` metrics) to a fresh sqlite store in a temporary folder, starts ``mlflow ui`` on 127.0.0.1, and opens
the link atdrone prints (:func:`atdrone.tracking.ui_link`) in browser profiles that have never seen MLflow
(what a new user's browser is). It passes when the page shows the runs table (not the GenAI view, "Traces")
with a ``validation_SUC_best`` column, and the same link's chart view (``compareRunsMode=CHART``) shows the
numbers first (the "Model metrics" section) and no empty section (e.g. ``budget``, whose metrics only the
folded generation run has); with ``--screenshot`` it saves the runs page. ``--bare`` (the link without its
parameters) and ``--no-view`` (the experiment without atdrone's view) show what the checks catch: both fail.
Needs Chromium (Debian: ``apt-get install chromium``); about a minute. Exit 0 on success, 1 with the reason.
``tests/browser/test_mlflow_view.py`` runs it under pytest (skipped without Chromium).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RUN_NAME = "browser-check-run"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


SUC_COLUMN = "validation_SUC_best"  # the population's best member on the validation zoo (population_columns)


def _log_run(uri: str) -> None:
    """A population-shaped run: what the runs table and the charts of a real one are made of."""
    from atdrone.tracking import Tracker, population_columns

    tracker = Tracker(uri)
    with tracker.run("atdrone_browser_check", RUN_NAME) as parent:
        tracker.log_params({"algorithm": "hola", "task": "4p2e1o"})
        for step, value in enumerate((12.0, 21.5, 30.5)):
            tracker.log_metrics({"gen/zoo3_SUC_best_48ep": value, "gen/population_size": 2.0 + step}, step=step)
        with tracker.run("atdrone_browser_check", "gen-0", nested=True):
            tracker.log_metrics({"budget/env_steps": 4096.0, "pop/size": 2.0}, step=0)
            tracker.log_series({"pop/rho": [0.25, 0.75]})
        rows = [
            {"member": "hola-g0-0", "validation_SUC": 41.5, "zoo3_SUC": 38.0},
            {"member": "hola-g0-1", "validation_SUC": 55.0, "zoo3_SUC": 48.5},
        ]
        tracker.log_metrics(population_columns(rows, "validation", "zoo3", best="hola-g0-1"), step=3, run_id=parent)


def _forget_view(uri: str) -> None:
    """Delete atdrone's view from the check's experiment (``--no-view``: what MLflow shows without it)."""
    import mlflow

    from atdrone.tracking_views import VIEW_TAG

    client = mlflow.MlflowClient(uri)
    found = client.get_experiment_by_name("atdrone_browser_check")
    assert found is not None
    client.delete_experiment_tag(found.experiment_id, VIEW_TAG)


def _wait_up(url: str, seconds: float) -> None:
    deadline = time.monotonic() + seconds
    while True:
        try:
            urllib.request.urlopen(url, timeout=2).close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def _chromium_args(binary: str, profile: Path, *args: str) -> list[str]:
    return [
        binary,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--no-first-run",
        f"--user-data-dir={profile}",
        "--window-size=1400,900",
        "--virtual-time-budget=15000",
        *args,
    ]


def _chromium(binary: str, profile: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(_chromium_args(binary, profile, *args), capture_output=True, text=True, timeout=120)


def _dump_doms(binary: str, folder: Path, links: list[str]) -> list[str]:
    """The DOM of each link after its scripts ran, each in a fresh profile, the browsers side by side."""
    procs = [
        subprocess.Popen(
            _chromium_args(binary, folder / f"profile{n}", "--dump-dom", link),
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
        )
        for n, link in enumerate(links)
    ]
    return [proc.communicate(timeout=180)[0] for proc in procs]


SECTION = re.compile(
    r'data-testid="experiment-view-compare-runs-section-header".*?>([^<>]+)</div><div[^>]*>\((\d+)\)</div>', re.S
)


def chart_sections(dom: str) -> list[tuple[str, int]]:
    """The chart view's sections, in order: each one's name and how many charts it shows (its header's count,
    which leaves out the empty charts MLflow hides; a chart itself may not be drawn yet when the DOM is taken)."""
    return [(name, int(count)) for name, count in SECTION.findall(dom)]


def _problems(table: str, charts: str) -> list[str]:
    """What the runs page (``table``) and its chart view (``charts``) lack of atdrone's view."""
    problems = []
    if RUN_NAME not in table:
        problems.append(f"the run {RUN_NAME!r} is not on the page")
    if "No data available" in table or "Detect Issues" in table or "Runs</" not in table:
        problems.append("the page shows the GenAI view, not the runs table")
    if f'data-testid="sort-header-{SUC_COLUMN}"' not in table:
        problems.append(f"the runs table has no {SUC_COLUMN} column")
    sections = chart_sections(charts)
    empty = [name for name, count in sections if count == 0]
    if not sections:
        problems.append("the chart view shows no chart section")
    elif sections[0][0] != "Model metrics":
        problems.append(f"the chart view opens on {sections[0][0]!r}, not the population's numbers (Model metrics)")
    if empty or "No charts in this section" in charts:
        problems.append(f"the chart view has empty sections: {', '.join(empty)}")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--screenshot", type=Path, default=None, help="save the page as this PNG")
    parser.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    parser.add_argument(
        "--bare", action="store_true", help="open the experiment without the link's parameters (the check fails)"
    )
    parser.add_argument("--no-view", action="store_true", help="delete atdrone's view first (the check fails)")
    args = parser.parse_args(argv)
    if not args.chromium:
        print("mlflow_view: no chromium on PATH (apt-get install chromium)", file=sys.stderr)
        return 1
    from atdrone.tracking import Tracker, ui_link

    with tempfile.TemporaryDirectory(prefix="atdrone-mlflow-view-") as tmp:
        folder = Path(tmp)
        uri = f"sqlite:///{folder / 'mlflow.db'}"
        port = _free_port()
        Tracker(uri)  # the store's schema, before the server and the run share it
        mlflow = Path(sys.executable).with_name("mlflow")
        command = [str(mlflow), "ui", "--backend-store-uri", uri, "--host", "127.0.0.1", "--port", str(port)]
        server = subprocess.Popen(
            [*command, "--workers", "1"],  # one: four (the default) start side by side, half a minute on two cores
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true"},
        )
        try:
            _log_run(uri)  # while the server starts
            if args.no_view:
                _forget_view(uri)
            link = ui_link("atdrone_browser_check", uri).replace(":5000/", f":{port}/")
            if args.bare:
                link = link.split("?")[0]
            _wait_up(f"http://127.0.0.1:{port}/health", 120)
            # the runs tab itself: the redirect from the experiment's address drops compareRunsMode
            tab = re.sub(r"#/experiments/(\d+)(\?|$)", r"#/experiments/\1/runs\2", link)
            chart_link = f"{tab}{'&' if '?' in tab else '?'}compareRunsMode=CHART"
            table, charts = _dump_doms(args.chromium, folder, [link, chart_link])
            if args.screenshot is not None:
                args.screenshot.parent.mkdir(parents=True, exist_ok=True)
                _chromium(args.chromium, folder / "profile-shot", f"--screenshot={args.screenshot.resolve()}", link)
        finally:
            server.terminate()
            server.wait(timeout=30)
    problems = _problems(table, charts)
    if problems:
        print(f"mlflow_view: {link}: " + "; ".join(problems), file=sys.stderr)
        return 1
    shot = f"; screenshot {args.screenshot}" if args.screenshot is not None else ""
    print(f"mlflow_view: ok, {link} opens the runs table with {SUC_COLUMN}, and charts without empty sections{shot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
