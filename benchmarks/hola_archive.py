"""Keep a long hola_report study across machines: the finished runs' files that the evaluate and
report phases read, copied into a committed folder, and copied back where a fresh checkout lacks them.

A study of many hours runs in chunks over sessions whose ``reports/`` (not committed) may not
survive. ``save`` copies, for every finished run (``population.csv`` present), what the later phases
read: ``population.csv``, ``service_state.json``, ``compute.json``, each generation's
``hypergraph.json`` and the checkpoints of the members they evaluate (the final learner; SP's member
at HOLA's learner samples), about 0.4 MB a run; plus ``eval/`` and ``crossplay/``. ``restore``
copies them back into ``--out`` where missing, so ``hola_report.py --resume`` skips the runs and
evaluations they hold. Both are idempotent and write each file atomically.

Usage: python benchmarks/hola_archive.py save|restore --out reports/hola_power \
           --archive benchmarks/results/hola_power/archive
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

from atdrone.fileio import atomic_write_bytes

RUN_FILES = ("population.csv", "service_state.json", "compute.json")


def _report_module() -> ModuleType:
    """hola_report.py beside this script (its final_member and sp_at_samples choose what to keep)."""
    spec = importlib.util.spec_from_file_location("hola_report", Path(__file__).with_name("hola_report.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _members_needed(run_dir: Path, out: Path) -> set[str]:
    """The members the evaluate phase loads from a finished run."""
    report = _report_module()
    task, rest = run_dir.name.split("-", 1)
    algorithm, seed_part = rest.rsplit("-s", 1)
    if "+" in algorithm:
        algorithm = algorithm.split("+", 1)[0]
    members = {report.final_member(run_dir, algorithm)}
    if algorithm == "sp":
        args = argparse.Namespace(out=str(out))
        extra = report.sp_at_samples(run_dir, task, int(seed_part), args)
        if extra is not None:
            members.add(extra)
    return members


def _copy(src: Path, dst: Path) -> bool:
    """Copy one file atomically unless ``dst`` already holds the same bytes; True if written."""
    data = src.read_bytes()
    if dst.exists() and dst.read_bytes() == data:
        return False
    dst.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(dst, data)
    return True


def _files_of(run_dir: Path, out: Path) -> list[Path]:
    files = [run_dir / name for name in RUN_FILES if (run_dir / name).exists()]
    files += sorted((run_dir / "generations").glob("*/hypergraph.json"))
    files += sorted((run_dir / "generations").glob("*/pi0.json"))  # which Pi_0 members are which skill level
    files += [run_dir / "members" / f"{m}.pt" for m in sorted(_members_needed(run_dir, out))]
    return files


def save(out: Path, archive: Path) -> int:
    """Copy the finished runs' kept files and the evaluations into ``archive``; the files written."""
    written = 0
    # SP's member at HOLA's samples needs the HOLA run first: sorted names put '-hola' before '-sp'
    for run_dir in sorted((out / "runs").glob("*")):
        if not (run_dir / "population.csv").exists():
            continue
        for path in _files_of(run_dir, out):
            written += _copy(path, archive / path.relative_to(out))
    for sub in ("eval", "crossplay"):
        for path in sorted((out / sub).glob("*.json")):
            written += _copy(path, archive / path.relative_to(out))
    return written


def restore(archive: Path, out: Path) -> int:
    """Copy archived files into ``out`` where missing (a file already there is never overwritten)."""
    written = 0
    for path in sorted(p for p in archive.rglob("*") if p.is_file()):
        target = out / path.relative_to(archive)
        if not target.exists():
            written += _copy(path, target)
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=["save", "restore"])
    parser.add_argument("--out", required=True, help="the study's working folder (hola_report --out)")
    parser.add_argument("--archive", required=True, help="the committed copy")
    args = parser.parse_args()
    out, archive = Path(args.out), Path(args.archive)
    n = save(out, archive) if args.action == "save" else restore(archive, out)
    print(json.dumps({"action": args.action, "files_written": n}), file=sys.stderr)


if __name__ == "__main__":
    main()
