"""What the process runs on: accelerator detection, weight dtypes, torch threads, glibc malloc tuning.

The bottom layer with `posttrain.errors`: it imports nothing else of posttrain, so the config checks
(`config.resolve` refuses half dtypes on CPU), the model loaders and `loop.setup` share one answer.
"""
from __future__ import annotations

import ctypes
import os
import sys

import torch

DTYPES: dict[str, torch.dtype] = {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}
_malloc_tuned = False


def has_accelerator_device() -> bool:
    """A CUDA, XPU or MPS device is visible to torch."""
    if torch.cuda.is_available():
        return True
    xpu = getattr(torch, "xpu", None)
    if xpu is not None and xpu.is_available():
        return True
    mps = getattr(torch.backends, "mps", None)
    return bool(mps is not None and mps.is_available())


def dtype_problem(name: str) -> str | None:
    """Why weights in dtype `name` (a `model.dtype` value) cannot be used on this machine, or None."""
    if name == "float32":
        return None
    if has_accelerator_device():
        return None
    return (f"model.dtype={name}: no GPU found; on CPU posttrain trains float32 weights ({name} weights would "
            "train without an fp32 master copy, and many CPUs have no bf16 matmul units); use model.dtype=float32, "
            "and for bf16 compute over fp32 weights set run.mixed_precision=bf16 (or auto)")


def cpu_flags() -> set[str]:
    """The CPU feature flags of /proc/cpuinfo (empty where there is none)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def native_bf16() -> bool:
    """bf16 matmuls run natively here: a CUDA GPU with bf16 support, or a CPU with AVX512-BF16 or AMX-BF16
    (there bf16 autocast is 2-3x the fp32 matmul rate; without them it emulates bf16 and is slower)."""
    if torch.cuda.is_available():
        return bool(torch.cuda.is_bf16_supported())
    return bool({"avx512_bf16", "amx_bf16"} & cpu_flags())


def mixed_precision(setting: str) -> str | None:
    """`run.mixed_precision` -> what `accelerate.Accelerator(mixed_precision=...)` gets: "no" -> None (what
    `accelerate launch` was given, else none), "bf16" -> "bf16", "auto" -> "bf16" where `native_bf16()`, else None."""
    if setting not in ("no", "bf16", "auto"):
        raise ValueError(f"run.mixed_precision must be no, bf16 or auto, got {setting!r}")
    if setting == "bf16" or (setting == "auto" and native_bf16()):
        return "bf16"
    return None


def set_threads(threads: int) -> None:
    """torch's intra-op threads (`run.threads`); 0 keeps torch's default."""
    if threads > 0:
        torch.set_num_threads(threads)


def tune_malloc() -> bool:
    """Raise glibc's mmap threshold (32 MiB) and trim threshold (512 MiB), once per process, so the
    decode loop's per-step activations (up to a few MiB at large batch) are recycled from the heap
    instead of being mmapped, page-faulted and unmapped every step, and freed memory is not handed
    back to the OS between steps (faster forwards on CPU: see RESULTS.md). Process-wide (it also
    benefits anything else running); off glibc, or with POSTTRAIN_NO_MALLOPT=1 in the environment,
    it does nothing."""
    global _malloc_tuned
    if _malloc_tuned:
        return True
    _malloc_tuned = True
    if not sys.platform.startswith("linux") or os.environ.get("POSTTRAIN_NO_MALLOPT"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
        return bool(libc.mallopt(M_MMAP_THRESHOLD, 32 << 20)) and bool(libc.mallopt(M_TRIM_THRESHOLD, 512 << 20))
    except (OSError, AttributeError):
        return False
