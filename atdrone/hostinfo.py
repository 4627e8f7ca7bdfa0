"""What decides a float result on this host: its CPU and the kernels numpy and torch dispatch to on it.

An evaluation is deterministic on one machine; on another, numpy's SIMD loops or torch's CPU kernels may round
differently and turn an episode. Two hosts with the same :func:`float_kernels` run the same code paths, so a
result measured on one replays bit for bit on the other; the benchmark records it with every cell it evaluates.
"""

from __future__ import annotations

import platform
from pathlib import Path


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :mod:`platform` knows."""
    info = Path("/proc/cpuinfo")
    text = info.read_text() if info.is_file() else ""
    names = [line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("model name")]
    return names[0] if names else (platform.processor() or platform.machine())


def float_kernels() -> dict[str, str]:
    """This host's CPU, numpy's version and the SIMD targets it dispatches to here, torch's version and CPU
    capability: the things an evaluation's rounding depends on."""
    import importlib

    import numpy as np
    import torch

    umath = importlib.import_module("numpy._core._multiarray_umath")  # where numpy keeps its dispatch tables
    features = getattr(umath, "__cpu_features__", {})
    targets = [t for t in getattr(umath, "__cpu_dispatch__", ()) if features.get(t)]
    return {
        "cpu": cpu_model(),
        "numpy": f"{np.__version__} {','.join(targets) or 'baseline'}",
        "torch": f"{torch.__version__} {torch.backends.cpu.get_cpu_capability()}",
    }
