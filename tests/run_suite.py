"""The whole test suite as `make test` runs it: the simulated flights beside everything else.

The deploy flights (tests/test_deploy.py, tests/test_simfleet.py) run in real time on a
scaled clock and mostly wait for it (about a third of a core); the rest (Ray, training,
evaluation) is CPU-bound. So the flights run as their own pytest session at normal
priority while the rest runs on two xdist workers at ``nice`` +15: the flights get the CPU
when their clock needs it (their loop is never starved by a Ray test, as it could be on a
shared worker), and the waiting is no longer added to the suite's time.

    python tests/run_suite.py [PYTEST ARGS...]   (passed to both sessions)

The main session prints as it goes; the flights' output follows it. The exit status is
the first non-zero of the two (0 when both passed). Ctrl-C stops both.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

FLIGHTS = ("tests/test_deploy.py", "tests/test_simfleet.py")
# CFS weights: a nice 0 thread 1024, nice 15 36; the main session runs some 20 processes (two Ray sessions),
# so at +5 (335 each) a flight thread could get as little as an eighth of a core; at +15 it gets what it asks
NICE = 15


def main(argv: list[str]) -> int:
    root = Path(__file__).resolve().parent.parent
    pytest = [sys.executable, "-m", "pytest", "-q"]
    with tempfile.TemporaryDirectory(prefix="atdrone-flights-") as tmp:
        log_path = Path(tmp) / "flights.log"
        with open(log_path, "w") as log:
            flights = subprocess.Popen(
                [*pytest, "-p", "no:cacheprovider", "--basetemp", str(Path(tmp) / "base"), *FLIGHTS, *argv],
                cwd=root,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
            rest = subprocess.Popen(
                [*pytest, "-n", "2", "--dist", "loadgroup", *(f"--ignore={f}" for f in FLIGHTS), *argv],
                cwd=root,
                preexec_fn=lambda: os.nice(NICE),
            )
            try:
                rest_status = rest.wait()
                print("\n---- the simulated flights (tests/test_deploy.py, tests/test_simfleet.py) ----", flush=True)
                flight_status = flights.wait()
            except KeyboardInterrupt:
                for proc in (rest, flights):
                    proc.send_signal(signal.SIGINT)
                for proc in (rest, flights):
                    proc.wait()
                return 130
        sys.stdout.write(log_path.read_text())
    return rest_status or flight_status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
