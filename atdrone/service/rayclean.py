"""Ray processes a dead local Ray left behind, found and ended before a new local Ray starts.

A driver killed with SIGKILL takes its GCS and raylet with it, but their children (the dashboard and
runtime-env agents, idle workers) notice only when they next look, and on a busy host they live on
for minutes as orphans, holding memory and a share of the CPU. :func:`clean_orphans` ends them: every
Ray process of this user whose session (the ``/tmp/ray/session_*`` folder in its command line or its
open files) has no live raylet or GCS left and no live driver. A process of a live session (another run's
local Ray, a ``ray start`` head, a driver's Ray shutting down) is never touched, nor a process whose session
cannot be read. Linux only (``/proc``);
elsewhere it finds nothing.
"""

from __future__ import annotations

import logging
import os
import re
import signal
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)
PROC = Path("/proc")
_SESSION = re.compile(r"/session_\d{4}-\d\d-\d\d_[0-9_\-]+")
_DAEMONS = ("raylet", "gcs_server")  # a session with one of these alive is live


@dataclass(frozen=True)
class RayProcess:
    """A process of some Ray session: its pid, parent, program (``argv[0]``, whole), title (the command line's
    first 80 characters) and session folder name."""

    pid: int
    ppid: int
    program: str
    title: str
    session: str

    @property
    def daemon(self) -> bool:
        """A GCS or raylet: known by the program's name, never by the title, which a long install path cuts."""
        return _is_daemon(self.program)


def _read(path: Path) -> str:
    try:
        return path.read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return ""


def _session(pid: int, cmdline: str) -> str:
    """The session folder's name, from the command line, else from the open files (an agent retitles itself)."""
    found = _SESSION.search(cmdline)
    if found is None:
        try:
            for fd in (PROC / str(pid) / "fd").iterdir():
                found = _SESSION.search(os.readlink(fd))
                if found is not None:
                    break
        except OSError:
            return ""
    return found.group(0).lstrip("/") if found else ""


def _status(pid: int) -> tuple[int, int, str]:
    """(parent pid, real uid, state letter) from /proc/<pid>/status; (0, -1, "") when it is gone."""
    try:
        status = (PROC / str(pid) / "status").read_text(errors="replace")
    except OSError:
        return 0, -1, ""
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    try:
        return int(fields["PPid"]), int(fields["Uid"].split()[0]), fields["State"].split()[0]
    except (KeyError, ValueError, IndexError):
        return 0, -1, ""


def _is_daemon(program: str) -> bool:
    """A GCS or raylet binary of the ray package."""
    return Path(program).name in _DAEMONS and "/ray/" in program


def _is_ray(cmdline: str) -> bool:
    """A Ray worker (``ray::...``), a Ray daemon binary, or Python running a script of the ray package."""
    if cmdline.startswith("ray::"):
        return True
    argv = cmdline.split()
    if not argv:
        return False
    if Path(argv[0]).name in _DAEMONS:
        return _is_daemon(argv[0])
    return any("/ray/" in a and a.endswith(".py") for a in argv[1:3])


def ray_processes() -> list[RayProcess]:
    """Every live process of this user that belongs to a Ray session (zombies aside)."""
    found: list[RayProcess] = []
    if not PROC.is_dir():
        return found
    me = os.getuid()
    for entry in PROC.iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        pid = int(entry.name)
        cmdline = _read(entry / "cmdline")
        if not _is_ray(cmdline):
            continue
        ppid, uid, state = _status(pid)
        if uid != me or state in ("Z", "X", ""):
            continue
        session = _session(pid, cmdline)
        if session:
            found.append(RayProcess(pid, ppid, cmdline.split(" ", 1)[0], cmdline[:80], session))
    return found


def _starter(session: str) -> int:
    """The pid of the process that started a session: the last field of its name (Ray names it
    ``session_<date>_<time>_<microseconds>_<pid>``); 0 when the name has none."""
    last = session.rsplit("_", 1)[-1]
    return int(last) if last.isdigit() else 0


def orphans() -> list[RayProcess]:
    """The Ray processes whose session has neither a raylet nor a GCS alive, nor its driver.

    A driver's ``ray.shutdown()`` ends its raylet and GCS first, then one by one the processes it started itself
    (log monitor, dashboard, autoscaler monitor), waiting up to seconds for each on a busy host: meanwhile they
    are a live driver's children, never orphans. A process whose parent is its session's starter is one (a dead
    driver's children have another parent, so a reused pid is never taken for it). The daemons are looked for
    again after the processes are listed: a Ray starting meanwhile starts its GCS before anything else of its
    session, so a process listed is never taken for an orphan for want of a daemon that started while the list
    was read."""
    processes = ray_processes()
    live = {p.session for p in processes if p.ppid == _starter(p.session)}
    live |= {p.session for p in ray_processes() if p.daemon}
    return [p for p in processes if p.session not in live]


def clean_orphans() -> list[RayProcess]:
    """End (SIGKILL) the Ray processes of dead sessions; the ones ended. Never raises."""
    try:
        left = orphans()
    except Exception as exc:  # pragma: no cover - /proc unreadable: nothing is ended
        log.debug("could not list Ray processes: %s", exc)
        return []
    ended = []
    for p in left:
        try:
            os.kill(p.pid, signal.SIGKILL)
            ended.append(p)
        except OSError:  # gone by itself meanwhile, or not ours
            continue
    if ended:
        sessions = sorted({p.session for p in ended})
        log.warning(
            "ended %d Ray process(es) a killed run left behind (%s): %s",
            len(ended),
            ", ".join(sessions),
            ", ".join(f"{p.pid} {Path(p.program).name}" for p in ended),
        )
    return ended
