"""Re-write checkpoints whose header has no ``header_sha256`` (written before it existed), weights unchanged.

    python benchmarks/upgrade_checkpoints.py configs/zoos/checkpoints/*.pt

Each file is loaded (magic, payload sha256 and observation layout checked), then saved
again with its own header, so the new file carries the header digest; the payload and
its sha256 stay as they were. Prints JSON: per file, the payload sha256 before and after.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

from atdrone.models.checkpoint import HEADER_DIGEST, load_checkpoint, read_header, save_checkpoint


def upgrade(path: Path) -> dict[str, object]:
    """Add the header digest to one checkpoint; a file that has one is left alone."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        header = read_header(path)
        if HEADER_DIGEST in header:
            return {"file": str(path), "upgraded": False, "sha256": header["sha256"]}
        model, header = load_checkpoint(path)
    keep = {k: v for k, v in header.items() if k not in ("format", "architecture", "sha256")}
    full = save_checkpoint(path, model, keep)
    return {"file": str(path), "upgraded": True, "sha256_before": header["sha256"], "sha256": full["sha256"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="checkpoint files (*.pt)")
    print(json.dumps([upgrade(p) for p in parser.parse_args().files], indent=2))


if __name__ == "__main__":
    main()
