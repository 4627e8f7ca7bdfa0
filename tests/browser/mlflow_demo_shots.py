"""Screenshots of what `make demo` leaves in MLflow, taken in a headless Chromium: the experiment's runs table,
the parent run (its description with the population table, the SUC metrics) and the registered model's page
(the champion alias).

    .venv/bin/python tests/browser/mlflow_demo_shots.py [--store sqlite:///mlflow.db] [--out-dir docs/img]

It starts ``mlflow ui`` on 127.0.0.1 (a free port) over the demo's store, opens the links atdrone prints
(model-training view) in a fresh browser profile, saves ``mlflow-experiment.png``, ``mlflow-parent-run.png``
and ``mlflow-model.png``, and checks each page shows what it should (exit 1
naming what is missing). Needs Chromium (Debian: ``apt-get install chromium``); about a minute.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mlflow_view import _chromium, _free_port, _wait_up

WIDE = "--window-size=1800,1000"  # room for the population's columns beside MLflow's assistant panel


def _links(store: str, experiment: str, port: int) -> dict[str, tuple[str, list[str]]]:
    """Each page to take: its link (on ``port``) and the texts it must show."""
    import mlflow

    from atdrone.tracking import ui_link, ui_model_link, ui_run_link

    client = mlflow.MlflowClient(store)
    found = client.get_experiment_by_name(experiment)
    if found is None:
        raise SystemExit(f"mlflow_demo_shots: no experiment {experiment!r} in {store} (run make demo first)")
    parents = [
        r
        for r in client.search_runs([found.experiment_id], order_by=["attributes.start_time DESC"])
        if "mlflow.parentRunId" not in r.data.tags
    ]
    parent = parents[0]
    champion = [k for k in parent.data.metrics if k.endswith("_SUC_champion")]
    model = f"atdrone-{experiment}"

    def here(link: str) -> str:
        return link.replace(":5000/", f":{port}/")

    return {
        "mlflow-experiment.png": (here(ui_link(experiment, store)), [parent.info.run_name]),
        "mlflow-parent-run.png": (here(ui_run_link(parent.info.run_id, store)), ["best member", *champion]),
        "mlflow-model.png": (here(ui_model_link(model)), [model, "champion"]),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--store", default="sqlite:///mlflow.db", help="the demo's tracking store")
    parser.add_argument("--experiment", default="hola_quick", help="the demo's experiment (default hola_quick)")
    parser.add_argument("--out-dir", type=Path, default=Path("docs/img"), help="where the PNGs go")
    parser.add_argument("--chromium", default=shutil.which("chromium") or shutil.which("chromium-browser"))
    args = parser.parse_args(argv)
    if not args.chromium:
        print("mlflow_demo_shots: no chromium on PATH (apt-get install chromium)", file=sys.stderr)
        return 1
    from atdrone.tracking import tracking_uri

    store = tracking_uri(args.store)
    port = _free_port()
    pages = _links(store, args.experiment, port)
    mlflow = Path(sys.executable).with_name("mlflow")
    server = subprocess.Popen(
        [str(mlflow), "ui", "--backend-store-uri", store, "--host", "127.0.0.1", "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "MLFLOW_DISABLE_TELEMETRY": "true"},
    )
    problems = []
    try:
        _wait_up(f"http://127.0.0.1:{port}/health", 120)
        args.out_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(prefix="atdrone-mlflow-shots-") as tmp:
            for n, (name, (link, expected)) in enumerate(pages.items()):
                dom = _chromium(args.chromium, Path(tmp) / f"dom{n}", WIDE, "--dump-dom", link).stdout
                missing = [text for text in expected if text not in dom]
                if missing:
                    problems.append(f"{name} ({link}) does not show {', '.join(map(repr, missing))}")
                shot = (args.out_dir / name).resolve()
                _chromium(args.chromium, Path(tmp) / f"shot{n}", WIDE, f"--screenshot={shot}", link)
                print(f"mlflow_demo_shots: {shot} <- {link}")
    finally:
        server.terminate()
        server.wait(timeout=30)
    if problems:
        print("mlflow_demo_shots: " + "; ".join(problems), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
