"""Tensors plus JSON in one file that loads without unpickling.

The payload is the safetensors format (a JSON index, then raw little-endian tensor
bytes); the file's JSON document (anything ``json.dumps`` takes) travels in the
safetensors metadata under one key, together with the sha256 of the tensor bytes, so a
damaged or truncated file is refused rather than half-loaded. Files are written to a
temp name and renamed (:mod:`atdrone.fileio`).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save

from atdrone.errors import UserError
from atdrone.fileio import atomic_write_bytes

DOC_KEY = "atdrone"
DIGEST_KEY = "sha256"


class TensorFileError(UserError, ValueError):
    """A tensor file is missing, damaged or not one of ours."""


def tensor_digest(tensors: Mapping[str, torch.Tensor]) -> str:
    """sha256 over the tensors' names, dtypes, shapes and bytes, in name order."""
    h = hashlib.sha256()
    for name in sorted(tensors):
        t = tensors[name].detach().cpu().contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")  # 0-dim too
    return h.hexdigest()


def encode(tensors: Mapping[str, torch.Tensor], document: Mapping[str, Any]) -> bytes:
    """The bytes of a tensor file holding ``tensors`` and the JSON ``document``."""
    clean = {k: v.detach().cpu().contiguous() for k, v in tensors.items()}
    # one metadata key: safetensors writes its metadata map in no fixed order, and the bytes must not vary
    meta = {DOC_KEY: json.dumps({"document": document, DIGEST_KEY: tensor_digest(clean)}, sort_keys=True)}
    return st_save(clean, metadata=meta)


def decode(data: bytes, source: str = "<bytes>") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Tensors and JSON document of :func:`encode`'s bytes; TensorFileError when damaged."""
    try:
        tensors = st_load(data)
        header_len = int.from_bytes(data[:8], "little")
        meta = json.loads(data[8 : 8 + header_len]).get("__metadata__", {})
        if DIGEST_KEY in meta:  # the first layout: document and digest under two keys
            document, digest = json.loads(meta[DOC_KEY]), meta[DIGEST_KEY]
        else:
            both = json.loads(meta[DOC_KEY])
            document, digest = both["document"], both[DIGEST_KEY]
    except Exception as exc:  # safetensors, JSON and key errors alike
        raise TensorFileError(f"{source}: not a readable atdrone tensor file ({type(exc).__name__}: {exc})") from None
    if tensor_digest(tensors) != digest:
        raise TensorFileError(f"{source}: corrupted tensors (sha256 mismatch)")
    return tensors, document


def save_tensors(
    path: str | os.PathLike[str], tensors: Mapping[str, torch.Tensor], document: Mapping[str, Any]
) -> Path:
    """Write ``tensors`` and ``document`` to ``path`` atomically."""
    return atomic_write_bytes(path, encode(tensors, document))


def load_tensors(path: str | os.PathLike[str]) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a file written by :func:`save_tensors`."""
    p = Path(path)
    if not p.is_file():
        raise TensorFileError(f"{p}: no such file")
    return decode(p.read_bytes(), str(p))
