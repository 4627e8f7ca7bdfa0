"""The whole test suite as `make test` runs it: the simulated flights beside everything else.

The deploy flights (tests/test_deploy.py, tests/test_deploy_faults.py, tests/test_deploy_backup.py,
tests/test_simfleet.py) run in real time on a scaled clock and mostly wait for it (about a third of a
core); the rest (Ray, training, evaluation) is CPU-bound. So the flights run as their own pytest session at normal
priority while the rest runs on two xdist workers at ``nice`` +15: the flights get the CPU
when their clock needs it (their loop is never starved by a Ray test, as it could be on a
shared worker), and the waiting is no longer added to the suite's time. A command given
with ``--beside`` (``make test``: the type check, half a minute of one core from a fresh
clone) runs at the same time, at ``nice`` +15 too.

    python tests/run_suite.py [--beside CMD]... [PYTEST ARGS...]   (passed to both sessions)

The main session prints as it goes; the flights' output follows it, then each ``--beside``
command's. The exit status is the first non-zero of them all (0 when all passed). Ctrl-C
stops them all.
"""

from __future__ import annotations

import os
import shlex
import signal
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import IO

FLIGHTS = (
    "tests/test_deploy.py",
    "tests/test_deploy_faults.py",
    "tests/test_deploy_backup.py",
    "tests/test_simfleet.py",
)
# CFS weights: a nice 0 thread 1024, nice 15 36; the main session runs some 20 processes (two Ray sessions),
# so at +5 (335 each) a flight thread could get as little as an eighth of a core; at +15 it gets what it asks
NICE = 15


def _split(argv: list[str]) -> tuple[list[str], list[str]]:
    """(--beside commands, pytest arguments)."""
    beside, rest = [], list(argv)
    while "--beside" in rest:
        i = rest.index("--beside")
        if i + 1 >= len(rest):
            raise SystemExit("run_suite.py: --beside needs a command")
        beside.append(rest.pop(i + 1))
        rest.pop(i)
    return beside, rest


def _niced() -> None:
    os.nice(NICE)


def main(argv: list[str]) -> int:
    root = Path(__file__).resolve().parent.parent
    beside, args = _split(argv)
    # byte code cached: some 200 processes import atdrone (Ray workers, drivers, the CLI); with
    # PYTHONDONTWRITEBYTECODE set (as on this machine) each compiled its modules again, 0.15 s apiece
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    pytest = [sys.executable, "-m", "pytest", "-q"]
    with tempfile.TemporaryDirectory(prefix="atdrone-flights-") as tmp:
        logs: list[tuple[str, IO[str]]] = []
        procs: list[subprocess.Popen[bytes]] = []

        def start(title: str, cmd: list[str], log_name: str, nice: bool) -> None:
            log = open(Path(tmp) / log_name, "w+")  # noqa: SIM115 - closed below, after the process ends
            logs.append((title, log))
            procs.append(
                subprocess.Popen(
                    cmd, cwd=root, stdout=log, stderr=subprocess.STDOUT, preexec_fn=_niced if nice else None
                )
            )

        start(
            f"the simulated flights ({', '.join(FLIGHTS)})",
            [*pytest, "-p", "no:cacheprovider", "--basetemp", str(Path(tmp) / "base"), *FLIGHTS, *args],
            "flights.log",
            nice=False,
        )
        for i, command in enumerate(beside):
            start(command, shlex.split(command), f"beside{i}.log", nice=True)
        rest = subprocess.Popen(
            [*pytest, "-n", "2", "--dist", "loadgroup", *(f"--ignore={f}" for f in FLIGHTS), *args],
            cwd=root,
            preexec_fn=_niced,
        )
        try:
            statuses = [rest.wait()]
            for (title, log), proc in zip(logs, procs, strict=True):
                statuses.append(proc.wait())
                print(f"\n---- {title} ----", flush=True)
                log.seek(0)
                sys.stdout.write(log.read())
                log.close()
        except KeyboardInterrupt:
            for proc in (rest, *procs):
                proc.send_signal(signal.SIGINT)
            for proc in (rest, *procs):
                proc.wait()
            return 130
    return next((s for s in statuses if s), 0)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
