"""Ray job entrypoint: fly a population member on the drones next to the head node.

    ray job submit --address http://HEAD:8265 --working-dir . -- \
        python jobs/deploy.py configs/deploy/arena_4p2e1o.json [--arm] [--episodes N] [--tracking-uri URI]

A Ray job's entrypoint runs on the head node, so submit it to the head that sits next
to the arena (the Crazyradio and the motion-capture network). The arguments are those
of ``atdrone deploy`` (see ``atdrone deploy --help``); without --arm it is a dry run:
connect, preflight checks, the plan, nothing armed. Stopping the job (``ray job stop``)
sends SIGTERM: every drone lands, then one line (``jobs/deploy.py: interrupted; ...``: how
the drones ended, the flight log kept, the command that flies again) and status 143 (130
for SIGINT).
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # `--working-dir .` on nodes that only have the dependencies
    sys.path.insert(0, str(REPO_ROOT))

from atdrone.cli import main as cli_main  # noqa: E402 - after the sys.path set-up

PROG = "jobs/deploy.py"


def main(argv: list[str] | None = None) -> int:
    return cli_main(["deploy", *(sys.argv[1:] if argv is None else argv)], prog=PROG)


if __name__ == "__main__":
    sys.exit(main())
