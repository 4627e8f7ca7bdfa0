"""Policy checkpoints: a network's tensors behind a human-readable JSON header.

File layout (one file, ``*.pt``):
    line 1  ``ATDRONE-CHECKPOINT 1`` (the container; the header's ``format`` names the payload)
    line 2  the header, one line of JSON: format, architecture ({"class": name, **config},
            see :mod:`atdrone.models.architectures`), obs_layout_version, task, num_p,
            num_e, algorithm, config, seed, step, git_commit, metrics, created, sha256
            (of the payload bytes), header_sha256 (of the header's canonical JSON without
            this field, so every header field and, through sha256, the payload are covered)
    rest    the payload: format 2, the state_dict as a tensor file
            (:mod:`atdrone.models.tensorfile`, safetensors with its own digest);
            format 1 (legacy, older runs), ``torch.save`` of the state_dict.
``head -2 file.pt`` shows the provenance. Files are written to a temp name and
renamed. Loading checks the magic line, the header and its digest, the sha256 and the
observation layout, and refuses a mismatched, edited or corrupted file with a
:class:`CheckpointError`. A header without ``header_sha256`` (written before it existed)
loads with a warning; ``python benchmarks/upgrade_checkpoints.py FILE...`` gives such
files their digest (:func:`sign_header`; the payload untouched).
Format 2 loads without unpickling anything; format 1 goes through
``torch.load(weights_only=True)``, which unpickles tensors only.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import subprocess
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import nn

from atdrone.envs.core import OBS_LAYOUT_VERSION
from atdrone.fileio import atomic_write_bytes
from atdrone.models.architectures import CheckpointError, PolicyModel, build_model
from atdrone.models.tensorfile import TensorFileError, decode, encode

__all__ = [
    "FORMAT",
    "HEADER_DIGEST",
    "MAGIC",
    "REQUIRED",
    "CheckpointError",
    "header_digest",
    "load_checkpoint",
    "read_header",
    "save_checkpoint",
    "sign_header",
]

MAGIC = b"ATDRONE-CHECKPOINT 1\n"
FORMAT = 2  # the payload format written; 1 (torch.save) is still read
REQUIRED = ("architecture", "obs_layout_version", "task", "num_p", "num_e", "sha256")
HEADER_DIGEST = "header_sha256"


def git_commit() -> str:
    """The repository's HEAD commit, or "unknown" outside a git checkout."""
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=5
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _module(model: PolicyModel) -> nn.Module:
    if not isinstance(model, nn.Module):
        raise TypeError(f"a checkpoint holds a torch nn.Module, not {type(model).__name__}")
    return model


def save_checkpoint(path: str | Path, model: PolicyModel, header: dict[str, Any]) -> dict[str, Any]:
    """Write ``model``'s weights with ``header`` (task, num_p, num_e, ...) to ``path``; the full header.

    ``header`` may override git_commit and created (e.g. when re-writing an old file);
    format, architecture and sha256 always describe what is written.
    """
    payload = encode(_module(model).state_dict(), {})
    full = {
        "obs_layout_version": OBS_LAYOUT_VERSION,
        "git_commit": git_commit(),
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        **header,
        "format": FORMAT,
        "architecture": model.architecture(),
        "sha256": hashlib.sha256(payload).hexdigest(),
    }
    missing = [k for k in REQUIRED if k not in full]
    if missing:
        raise ValueError(f"checkpoint header lacks {missing}")
    full.pop(HEADER_DIGEST, None)
    full[HEADER_DIGEST] = header_digest(full)
    atomic_write_bytes(path, MAGIC + json.dumps(full, sort_keys=True).encode() + b"\n" + payload)
    return full


def header_digest(header: dict[str, Any]) -> str:
    """sha256 of a header's canonical JSON (sorted keys, compact), without the digest field itself."""
    body = {k: v for k, v in header.items() if k != HEADER_DIGEST}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def sign_header(path: str | Path, **changes: Any) -> dict[str, Any]:
    """Re-write a checkpoint's header with ``changes`` and a fresh header_sha256, the payload untouched.

    For tooling, not for hiding edits (the digest is a check against accidents and stale
    tools, not a signature with a secret): giving a header written before header_sha256
    existed its digest, or making test files of another atdrone version.
    """
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"\n", len(MAGIC))
    if not data.startswith(MAGIC) or end < 0:
        raise CheckpointError(f"{path}: not an atdrone checkpoint (bad magic line or header)")
    header = {**json.loads(data[len(MAGIC) : end]), **changes}
    header.pop(HEADER_DIGEST, None)
    header[HEADER_DIGEST] = header_digest(header)
    atomic_write_bytes(path, MAGIC + json.dumps(header, sort_keys=True).encode() + data[end:])
    return header


def read_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a checkpoint, without loading the weights (the sha256 is checked)."""
    return _read(path)[0]


def _read(path: str | Path) -> tuple[dict[str, Any], bytes]:
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: is a directory, not a checkpoint file")
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
    if HEADER_DIGEST not in header:
        warnings.warn(
            f"{path}: the header is not covered by a digest (written before header_sha256 existed); "
            "re-write it with benchmarks/upgrade_checkpoints.py",
            stacklevel=3,
        )
    elif header[HEADER_DIGEST] != header_digest(header):
        raise CheckpointError(f"{path}: the header was changed after it was written (header_sha256 mismatch)")
    payload = data[end + 1 :]
    if hashlib.sha256(payload).hexdigest() != header["sha256"]:
        raise CheckpointError(f"{path}: corrupted or truncated weights (sha256 mismatch with the header)")
    return header, payload


def _tensors(path: Path, header: dict[str, Any], payload: bytes) -> dict[str, torch.Tensor]:
    """The state_dict in ``payload``, by the header's format."""
    fmt = header.get("format", 1)
    if fmt == 2:
        try:
            return decode(payload, str(path))[0]
        except TensorFileError as exc:
            raise CheckpointError(str(exc)) from None
    if fmt == 1:  # legacy: torch.save, read back with the tensors-only unpickler
        try:
            state = torch.load(io.BytesIO(payload), weights_only=True, map_location="cpu")
        except Exception as exc:  # torch raises several kinds for a bad pickle
            raise CheckpointError(f"{path}: unreadable format 1 weights: {type(exc).__name__}: {exc}") from None
        if not isinstance(state, dict):
            raise CheckpointError(f"{path}: format 1 weights are not a state_dict")
        return state
    raise CheckpointError(f"{path}: unknown checkpoint format {fmt!r} (this atdrone reads 1 and 2)")


def load_checkpoint(path: str | Path, expect_task: str | None = None) -> tuple[PolicyModel, dict[str, Any]]:
    """Model (in eval mode) and header of a checkpoint; CheckpointError when it does not fit."""
    path = Path(path)
    header, payload = _read(path)
    if header["obs_layout_version"] != OBS_LAYOUT_VERSION:
        raise CheckpointError(
            f"{path}: observation layout v{header['obs_layout_version']}, this atdrone uses v{OBS_LAYOUT_VERSION}"
        )
    if expect_task is not None and header["task"] != expect_task:
        raise CheckpointError(f"{path}: trained on task {header['task']!r}, expected {expect_task!r}")
    if not isinstance(header["architecture"], dict):
        raise CheckpointError(f"{path}: the header's architecture is not a JSON object")
    try:
        model = build_model(header["architecture"])
    except CheckpointError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    module = _module(model)
    try:
        module.load_state_dict(_tensors(path, header, payload))
    except (TypeError, RuntimeError, KeyError) as exc:
        raise CheckpointError(f"{path}: weights do not match the architecture in the header: {exc}") from None
    module.eval()
    return model, header
