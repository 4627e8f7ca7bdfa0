"""Re-write checkpoints whose header has no ``header_sha256`` (written before it existed), weights unchanged.

    python benchmarks/upgrade_checkpoints.py configs/zoos/checkpoints/*.pt

Each file is loaded (magic, payload sha256, observation layout and weights checked), then
its header is written again with its digest (atdrone.models.checkpoint.sign_header); the
payload bytes and their sha256 stay as they were. Prints JSON, one entry per file.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

from atdrone.models.checkpoint import HEADER_DIGEST, load_checkpoint, read_header, sign_header


def upgrade(path: Path) -> dict[str, object]:
    """Add the header digest to one checkpoint; a file that has one is left alone."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if HEADER_DIGEST in read_header(path):
            return {"file": str(path), "upgraded": False}
        load_checkpoint(path)  # everything but the digest is checked before the header is signed
    header = sign_header(path)
    load_checkpoint(path)
    return {"file": str(path), "upgraded": True, "sha256": header["sha256"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="+", type=Path, help="checkpoint files (*.pt)")
    print(json.dumps([upgrade(p) for p in parser.parse_args().files], indent=2))


if __name__ == "__main__":
    main()
