"""Policy checkpoints: a torch state_dict behind a human-readable JSON header.

File layout (one file, ``*.pt``):
    line 1  ``ATDRONE-CHECKPOINT 1``
    line 2  the header, one line of JSON: format, architecture, obs_layout_version,
            task, num_p, num_e, algorithm, config, seed, step, git_commit, metrics,
            created, sha256 (of the payload)
    rest    the payload: ``torch.save`` of the state_dict
``head -2 file.pt`` shows the provenance. Files are written to a temp name and
renamed. Loading checks the magic line, the header, the sha256 and the observation
layout, and refuses a mismatched or corrupted file with a :class:`CheckpointError`.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import subprocess
from pathlib import Path
from typing import Any

import torch

from atdrone.envs.core import OBS_LAYOUT_VERSION
from atdrone.fileio import atomic_write_bytes
from atdrone.models.networks import ActorCritic, NetConfig

MAGIC = b"ATDRONE-CHECKPOINT 1\n"
REQUIRED = ("architecture", "obs_layout_version", "task", "num_p", "num_e", "sha256")


class CheckpointError(ValueError):
    """A checkpoint file is corrupted, truncated or does not fit what it is loaded for."""


def git_commit() -> str:
    """The repository's HEAD commit, or "unknown" outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def save_checkpoint(path: str | Path, model: ActorCritic, header: dict[str, Any]) -> dict[str, Any]:
    """Write ``model``'s weights with ``header`` (task, num_p, num_e, ... ) to ``path``."""
    buf = io.BytesIO()
    torch.save({k: v.detach().cpu() for k, v in model.state_dict().items()}, buf)
    payload = buf.getvalue()
    full = {
        "format": 1,
        "architecture": model.architecture(),
        "obs_layout_version": OBS_LAYOUT_VERSION,
        "git_commit": git_commit(),
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        **header,
        "sha256": hashlib.sha256(payload).hexdigest(),
    }
    missing = [k for k in REQUIRED if k not in full]
    if missing:
        raise ValueError(f"checkpoint header lacks {missing}")
    atomic_write_bytes(path, MAGIC + json.dumps(full, sort_keys=True).encode() + b"\n" + payload)
    return full


def read_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a checkpoint, without loading the weights."""
    return _read(path)[0]


def _read(path: str | Path) -> tuple[dict[str, Any], bytes]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise CheckpointError(f"{path}: not an atdrone checkpoint (bad magic line)")
    end = data.find(b"\n", len(MAGIC))
    if end < 0:
        raise CheckpointError(f"{path}: truncated header")
    try:
        header = json.loads(data[len(MAGIC) : end])
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"{path}: corrupted header: {exc}") from None
    if not isinstance(header, dict) or any(k not in header for k in REQUIRED):
        raise CheckpointError(f"{path}: header lacks one of {list(REQUIRED)}")
    payload = data[end + 1 :]
    if hashlib.sha256(payload).hexdigest() != header["sha256"]:
        raise CheckpointError(f"{path}: corrupted weights (sha256 mismatch with the header)")
    return header, payload


def load_checkpoint(path: str | Path, expect_task: str | None = None) -> tuple[ActorCritic, dict[str, Any]]:
    """Model and header of a checkpoint; CheckpointError when it does not fit."""
    header, payload = _read(path)
    if header["obs_layout_version"] != OBS_LAYOUT_VERSION:
        raise CheckpointError(
            f"{path}: observation layout v{header['obs_layout_version']}, this atdrone uses v{OBS_LAYOUT_VERSION}"
        )
    if expect_task is not None and header["task"] != expect_task:
        raise CheckpointError(f"{path}: trained on task {header['task']!r}, expected {expect_task!r}")
    arch = dict(header["architecture"])
    if arch.pop("class", None) != "ActorCritic":
        raise CheckpointError(f"{path}: unknown architecture {header['architecture']!r}")
    try:
        model = ActorCritic(NetConfig(**arch))
        state = torch.load(io.BytesIO(payload), weights_only=True, map_location="cpu")
        model.load_state_dict(state)
    except (TypeError, RuntimeError, KeyError) as exc:
        raise CheckpointError(f"{path}: weights do not match the architecture in the header: {exc}") from None
    model.eval()
    return model, header
