"""What the process runs on: accelerator detection, weight dtypes, torch threads, glibc malloc tuning.

The bottom layer with `posttrain.errors` (the only module of posttrain it imports), so the config checks
(`config.resolve` refuses half dtypes on CPU), the model loaders and `loop.setup` share one answer.
"""
from __future__ import annotations

import ctypes
import os
import sys
import time

import torch

from posttrain.errors import ConfigError

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


def default_device() -> torch.device:
    """Where a command without an Accelerator (`posttrain eval`, the reproductions' evaluations) puts its models:
    the first CUDA / XPU / MPS device when there is one, else the CPU (what accelerate would pick)."""
    if torch.cuda.is_available():
        return torch.device("cuda", torch.cuda.current_device())
    xpu = getattr(torch, "xpu", None)
    if xpu is not None and xpu.is_available():
        return torch.device("xpu", 0)
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        return torch.device("mps")
    return torch.device("cpu")


def dtype_problem(name: str) -> str | None:
    """Why weights in dtype `name` (a `model.dtype` value) cannot be used on this machine, or None."""
    if name == "float32":
        return None
    if has_accelerator_device():
        return None
    return (f"model.dtype={name}: no GPU found; on CPU posttrain trains float32 weights ({name} weights would "
            "train without an fp32 master copy, and many CPUs have no bf16 matmul units); use model.dtype=float32, "
            "and for bf16 compute over fp32 weights set run.mixed_precision=bf16 (or auto)")


def cpu_info() -> dict[str, str]:
    """The first processor's fields of /proc/cpuinfo ("model name", "cpu family", "model", "flags", ...); empty
    where there is none."""
    info: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break  # the end of the first processor's block
                key, _, value = line.partition(":")
                info.setdefault(key.strip(), value.strip())
    except OSError:
        pass
    return info


def cpu_flags() -> set[str]:
    """The CPU feature flags of /proc/cpuinfo (empty where there is none)."""
    return set(cpu_info().get("flags", "").split())


def cpu_model() -> str:
    """The CPU's model name with its family and model numbers (what RESULTS.md records with a figure)."""
    info = cpu_info()
    if not info:
        return "CPU not recorded"
    return f"{info.get('model name', 'unknown CPU')} (family {info.get('cpu family', '?')} model {info.get('model', '?')})"


def native_bf16() -> bool:
    """bf16 matmuls run faster than fp32 ones here: a CUDA GPU with bf16 support, or a CPU with AVX512-BF16 or
    AMX-BF16 on which `bf16_speedup()` measures at least BF16_MIN_SPEEDUP (on Zen 4 bf16 autocast beats the
    fp32 matmul rate). The flags alone do not say it: an Intel Xeon (family 6 model 207, AVX512-BF16 listed,
    AMX not exposed to the VM) ran bf16 matmuls slower than fp32 (measured: docs/results-archive.md, "bf16 on a CPU
    whose flags list AVX512-BF16 but whose bf16 matmuls are slow" and "Figures once kept in code comments");
    CPUs without the flags emulate bf16 and are slower still (no probe is run there). `bf16_forced()`
    (POSTTRAIN_BF16, a resumed run's recorded decision) answers first."""
    forced = bf16_forced()
    if forced is not None:
        return forced[0]
    if torch.cuda.is_available():
        return bool(torch.cuda.is_bf16_supported())
    return cpu_lists_bf16() and bf16_speedup() >= BF16_MIN_SPEEDUP


def cpu_lists_bf16() -> bool:
    """The CPU's flags list bf16 matmul units (AVX512-BF16 or AMX-BF16)."""
    return bool({"avx512_bf16", "amx_bf16"} & cpu_flags())


def probe_decides_bf16() -> bool:
    """`native_bf16` answers by `bf16_speedup()`: nothing forces the decision, there is no CUDA GPU, and the CPU
    lists bf16 units."""
    return bf16_forced() is None and not torch.cuda.is_available() and cpu_lists_bf16()


BF16_ENV = "POSTTRAIN_BF16"
_ENV_CHOICES = {"1": True, "on": True, "true": True, "0": False, "off": False, "false": False}
_bf16_pinned: bool | None = None


def bf16_forced() -> tuple[bool, str] | None:
    """What decides the `auto` settings (run.mixed_precision, rollout.dtype) without a measurement, and why:
    POSTTRAIN_BF16=1|0 in the environment (a user's explicit choice, e.g. for runs that must agree across
    machines or loads), else a decision pinned by `pin_bf16` (a resumed run keeps the one it started with);
    None: `native_bf16` decides by the hardware and the probe."""
    value = os.environ.get(BF16_ENV, "").strip().lower()
    if value:
        if value not in _ENV_CHOICES:
            raise ConfigError(f"{BF16_ENV}={value!r}: use 1 (bf16) or 0 (fp32) for the auto settings "
                              "(run.mixed_precision, rollout.dtype), or unset it to let a probe decide")
        return _ENV_CHOICES[value], f"{BF16_ENV}={value}"
    if _bf16_pinned is not None:
        return _bf16_pinned, "the decision recorded when this run started"
    return None


def pin_bf16(value: bool | None) -> None:
    """Make `native_bf16()` answer `value` in this process without probing (None: decide again). The CLI pins a
    resumed run's recorded decision, so a probe timed under another load cannot switch a run's precision
    half-way (`loop.recorded_bf16`)."""
    global _bf16_pinned
    _bf16_pinned = value


BF16_MIN_SPEEDUP = 1.2  # below this, bf16's rounding buys too little time to be worth choosing automatically
_bf16_speedups: dict[int, float] = {}


def bf16_speedup() -> float:
    """fp32 time / bf16 time of CPU matmuls at a decode shape (16 x 576 by 576 x 1536) and a training shape
    (256 x 576 by 576 x 1536), the smaller of the two (medians of 15 and 5 alternating calls: its cost,
    docs/results-archive.md, "Figures once kept in code comments");
    measured once per process and torch thread count (what `native_bf16` and so `auto` settings decide by)."""
    threads = torch.get_num_threads()
    if threads not in _bf16_speedups:
        _bf16_speedups[threads] = min(_matmul_time_ratio(rows, reps=reps) for rows, reps in ((16, 15), (256, 5)))
    return _bf16_speedups[threads]


def adopt_bf16_speedup(ratio: float) -> None:
    """Take `ratio` as this process's `bf16_speedup()` at the current thread count, without measuring. The
    processes of a multi-process run adopt process 0's measurement (`loop.share_bf16_probe`), so the `auto`
    settings decide alike on every rank."""
    _bf16_speedups[torch.get_num_threads()] = float(ratio)


def bf16_measured() -> float | None:
    """`bf16_speedup()` if it was measured at the current thread count (None: no probe ran)."""
    return _bf16_speedups.get(torch.get_num_threads())


def _matmul_time_ratio(rows: int, k: int = 576, n: int = 1536, reps: int = 5) -> float:
    g = torch.Generator().manual_seed(0)
    x, w = torch.randn(rows, k, generator=g), torch.randn(n, k, generator=g)
    pairs = {torch.float32: (x, w), torch.bfloat16: (x.bfloat16(), w.bfloat16())}
    times: dict = {dt: [] for dt in pairs}
    with torch.no_grad():
        for dt, (a, b) in pairs.items():  # warm-up: the kernels' one-off setup
            torch.nn.functional.linear(a, b)
        for _ in range(reps):
            for dt, (a, b) in pairs.items():
                t = time.perf_counter()
                torch.nn.functional.linear(a, b)
                times[dt].append(time.perf_counter() - t)
    med = {dt: sorted(ts)[len(ts) // 2] for dt, ts in times.items()}
    return med[torch.float32] / max(med[torch.bfloat16], 1e-9)


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
    """Keep freed memory in the process for reuse, once per process: glibc's trim threshold at 512 MiB (freed
    memory is not handed back to the OS between steps) and no mmap for large blocks (M_MMAP_MAX 0). A block
    above glibc's mmap threshold (32 MiB at most) is otherwise mapped, page-faulted (4 KiB pages, zeroed by the
    kernel) and unmapped at every allocation: a 49k-vocabulary model's logits, softmax and head gradients (tens
    to hundreds of MiB each, several per step) cost a real-size distillation run of 4 steps 2.3-3.5 M page faults
    and a third of its time in the kernel; from the heap they are reused, its steps ~10% faster and GRPO's ~5%,
    at ~3% more peak memory (docs/results-archive.md, "Page faults of large blocks"). The decode loop's per-step
    activations (a few MiB) are recycled the same way. Process-wide (it also benefits anything else running);
    off glibc, or with POSTTRAIN_NO_MALLOPT=1 in the environment, it does nothing."""
    global _malloc_tuned
    if _malloc_tuned:
        return True
    _malloc_tuned = True
    if not sys.platform.startswith("linux") or os.environ.get("POSTTRAIN_NO_MALLOPT"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4
        return bool(libc.mallopt(M_MMAP_MAX, 0)) and bool(libc.mallopt(M_TRIM_THRESHOLD, 512 << 20))
    except (OSError, AttributeError):
        return False
