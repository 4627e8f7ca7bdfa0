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
renamed. Loading checks the magic line, the header and its digest, the sha256, the
observation layout and that every weight is finite, and refuses a mismatched, edited or corrupted file with a
:class:`CheckpointError`: a header line that is not one JSON object with distinct keys
(at most ``MAX_HEADER_BYTES``), header fields of the wrong type or beyond their bounds
(num_p, num_e <= ``MAX_DRONES``), a file over ``MAX_FILE_BYTES``, and an architecture
over ``MAX_PARAMETERS`` or whose tensors do not have its shapes, before the network is
allocated. Legacy: a header without ``header_sha256`` (written before it existed) loads
with a warning when its payload matches its ``sha256`` (its other fields are then not
covered); ``python benchmarks/upgrade_checkpoints.py FILE...`` gives such files their
digest (:func:`sign_header`; the payload untouched). The committed zoo checkpoints
carry it.
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

from atdrone.config import MAX_DRONES
from atdrone.envs.core import OBS_LAYOUT_VERSION
from atdrone.fileio import atomic_write_bytes
from atdrone.models.architectures import MAX_PARAMETERS, CheckpointError, PolicyModel, build_model, skeleton
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
MAX_HEADER_BYTES = 2**20  # a header is a few KB (the run's config included)
# the largest file a checkpoint can be: a header and MAX_PARAMETERS float64 weights
MAX_FILE_BYTES = len(MAGIC) + MAX_HEADER_BYTES + 8 * MAX_PARAMETERS + 2**20


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
    data = _file_bytes(path)
    end = _header_end(path, data)
    header = {**_parse_header(path, data[len(MAGIC) : end]), **changes}
    header.pop(HEADER_DIGEST, None)
    header[HEADER_DIGEST] = header_digest(header)
    atomic_write_bytes(path, MAGIC + json.dumps(header, sort_keys=True).encode() + data[end:])
    return header


def read_header(path: str | Path) -> dict[str, Any]:
    """The JSON header of a checkpoint, without loading the weights (the sha256 is checked)."""
    return _read(path)[0]


def _file_bytes(path: Path) -> bytes:
    """The bytes of a checkpoint file; CheckpointError for a directory, a missing or an oversized file."""
    if path.is_dir():
        raise CheckpointError(f"{path}: is a directory, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise CheckpointError(f"{path}: {size:,} bytes, more than any checkpoint ({MAX_FILE_BYTES:,}): not one")
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise CheckpointError(f"{path}: not an atdrone checkpoint (bad magic line)")
    return data


def _header_end(path: Path, data: bytes) -> int:
    """The offset of the newline that ends the header line."""
    end = data.find(b"\n", len(MAGIC), len(MAGIC) + MAX_HEADER_BYTES + 1)
    if end < 0:
        raise CheckpointError(f"{path}: truncated header, or one over {MAX_HEADER_BYTES:,} bytes")
    return end


def _unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object whose keys are distinct (an edited header may name one twice)."""
    found: dict[str, Any] = {}
    for key, value in pairs:
        if key in found:
            raise ValueError(f"key {key!r} appears twice in one object")
        found[key] = value
    return found


def _parse_header(path: Path, line: bytes) -> dict[str, Any]:
    """The header line as a JSON object; CheckpointError when it is not one."""
    try:
        header = json.loads(line, object_pairs_hook=_unique)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        problem = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise CheckpointError(f"{path}: corrupted header: {problem}") from None
    if not isinstance(header, dict):
        raise CheckpointError(f"{path}: corrupted header: not a JSON object")
    return header


def _is_int(value: Any, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _check_fields(path: Path, header: dict[str, Any]) -> None:
    """CheckpointError unless the fields a loader reads have their types and bounds."""
    missing = [k for k in REQUIRED if k not in header]
    if missing:
        raise CheckpointError(f"{path}: header lacks {missing} (needs {list(REQUIRED)})")
    expected = {
        "task": ("a task name", isinstance(header["task"], str) and bool(header["task"])),
        "num_p": (f"a pursuer count in 1..{MAX_DRONES}", _is_int(header["num_p"], 1, MAX_DRONES)),
        "num_e": (f"an evader count in 1..{MAX_DRONES}", _is_int(header["num_e"], 1, MAX_DRONES)),
        "obs_layout_version": ("a version number", _is_int(header["obs_layout_version"], 0, 2**31)),
        "format": ("a format number", _is_int(header.get("format", 1), 0, 2**31)),
        "sha256": ("a hex digest", isinstance(header["sha256"], str)),
        "architecture": ("a JSON object", isinstance(header["architecture"], dict)),
    }
    for name, (what, ok) in expected.items():
        if not ok:
            raise CheckpointError(f"{path}: header field {name} must be {what}, got {header.get(name)!r:.80}")


def _read(path: str | Path) -> tuple[dict[str, Any], bytes]:
    path = Path(path)
    data = _file_bytes(path)
    end = _header_end(path, data)
    header = _parse_header(path, data[len(MAGIC) : end])
    if HEADER_DIGEST in header and header[HEADER_DIGEST] != header_digest(header):
        raise CheckpointError(f"{path}: the header was changed after it was written (header_sha256 mismatch)")
    _check_fields(path, header)
    if HEADER_DIGEST not in header:  # legacy: accepted when its payload matches its sha256 (below)
        warnings.warn(
            f"{path}: the header is not covered by a digest (written before header_sha256 existed); "
            "re-write it with benchmarks/upgrade_checkpoints.py",
            stacklevel=3,
        )
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


def _check_shapes(path: Path, model: PolicyModel, tensors: dict[str, torch.Tensor]) -> None:
    """CheckpointError unless ``tensors`` are exactly the state of ``model`` (names and shapes)."""
    expected = {name: tuple(t.shape) for name, t in model.state_dict().items()}
    found = {name: tuple(t.shape) if isinstance(t, torch.Tensor) else None for name, t in tensors.items()}
    if expected == found:
        return
    both = sorted(expected.keys() & found.keys())
    parts = {
        "missing": sorted(expected.keys() - found.keys()),
        "unexpected": sorted(found.keys() - expected.keys()),
        "shapes": [f"{n} {found[n]} != {expected[n]}" for n in both if found[n] != expected[n]],
    }
    detail = "; ".join(f"{what} {names[:3]}" for what, names in parts.items() if names)
    raise CheckpointError(f"{path}: weights do not match the architecture in the header: {detail}")


def _check_finite(path: Path, tensors: dict[str, torch.Tensor]) -> None:
    """CheckpointError when a weight is NaN or infinite (a diverged update saved): the policy would act on NaN."""
    bad = [name for name, t in tensors.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if bad:
        raise CheckpointError(
            f"{path}: non-finite weights (NaN or inf) in {', '.join(bad[:3])}: the policy is unusable"
        )


def load_checkpoint(path: str | Path, expect_task: str | None = None) -> tuple[PolicyModel, dict[str, Any]]:
    """Model (in eval mode) and header of a checkpoint; CheckpointError when it does not fit.

    Nothing is allocated for the network before the header has been checked and the
    payload's tensors (bounded by the file's size) match the declared architecture's
    names and shapes, taken from its meta-device :func:`~atdrone.models.architectures.skeleton`.
    """
    path = Path(path)
    header, payload = _read(path)
    if header["obs_layout_version"] != OBS_LAYOUT_VERSION:
        raise CheckpointError(
            f"{path}: observation layout v{header['obs_layout_version']}, this atdrone uses v{OBS_LAYOUT_VERSION}"
        )
    if expect_task is not None and header["task"] != expect_task:
        raise CheckpointError(f"{path}: trained on task {header['task']!r}, expected {expect_task!r}")
    try:
        shape = skeleton(header["architecture"])
    except CheckpointError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    tensors = _tensors(path, header, payload)
    _check_shapes(path, shape, tensors)
    _check_finite(path, tensors)
    model = build_model(header["architecture"])
    module = _module(model)
    try:
        module.load_state_dict(tensors)
    except (TypeError, RuntimeError, KeyError) as exc:
        raise CheckpointError(f"{path}: weights do not match the architecture in the header: {exc}") from None
    module.eval()
    return model, header
