"""Check in a headless Chromium that an atdrone experiment opens in MLflow's model-training view.

    .venv/bin/python tests/browser/mlflow_view.py [--screenshot docs/img/mlflow-runs.png] [--chromium PATH]

It logs one atdrone run (params, a metric, the experiment kind tag) to a fresh sqlite
store in a temporary folder, starts ``mlflow ui`` on 127.0.0.1, and opens the link
atdrone prints (:func:`atdrone.tracking.ui_link`) in a browser profile that has never
seen MLflow (what a new user's browser is). It passes when the page shows the run in
the runs table and not the GenAI view ("Traces"); with ``--screenshot`` it saves the
page. Not part of pytest: it needs Chromium (Debian: ``apt-get install chromium``) and
takes about a minute. Exit 0 on success, 1 with the reason otherwise.
"""

from __future__ import annotations

import argparse
import os
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


def _log_run(uri: str) -> str:
    from atdrone.tracking import Tracker, ui_link

    tracker = Tracker(uri)
    with tracker.run("atdrone_browser_check", RUN_NAME):
        tracker.log_params({"algorithm": "hola", "task": "4p2e1o"})
        for step, value in enumerate((12.0, 21.5, 30.5)):
            tracker.log_metrics({"zoo3/SUC": value}, step=step)
    return ui_link("atdrone_browser_check", uri)


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


def _chromium(binary: str, profile: Path, *args: str) -> subprocess.CompletedProcess[str]:
    command = [
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
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--screenshot", type=Path, default=None, help="save the page as this PNG")
    parser.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    parser.add_argument(
        "--bare", action="store_true", help="open the experiment without the view parameter (this check then fails)"
    )
    args = parser.parse_args(argv)
    if not args.chromium:
        print("mlflow_view: no chromium on PATH (apt-get install chromium)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory(prefix="atdrone-mlflow-view-") as tmp:
        folder = Path(tmp)
        uri = f"sqlite:///{folder / 'mlflow.db'}"
        port = _free_port()
        link = _log_run(uri).replace(":5000/", f":{port}/")
        if args.bare:
            link = link.split("?")[0]
        mlflow = Path(sys.executable).with_name("mlflow")
        server = subprocess.Popen(
            [str(mlflow), "ui", "--backend-store-uri", uri, "--host", "127.0.0.1", "--port", str(port)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env={**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true"},
        )
        try:
            _wait_up(f"http://127.0.0.1:{port}/health", 90)
            dom = _chromium(args.chromium, folder / "profile", "--dump-dom", link).stdout
            if args.screenshot is not None:
                args.screenshot.parent.mkdir(parents=True, exist_ok=True)
                _chromium(args.chromium, folder / "profile2", f"--screenshot={args.screenshot.resolve()}", link)
        finally:
            server.terminate()
            server.wait(timeout=30)
    problems = []
    if RUN_NAME not in dom:
        problems.append(f"the run {RUN_NAME!r} is not on the page")
    if "No data available" in dom or "Detect Issues" in dom or "Runs</" not in dom:
        problems.append("the page shows the GenAI view, not the runs table")
    if problems:
        print(f"mlflow_view: {link}: " + "; ".join(problems), file=sys.stderr)
        return 1
    shot = f"; screenshot {args.screenshot}" if args.screenshot is not None else ""
    print(f"mlflow_view: ok, {link} opens the runs table (model-training view){shot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
