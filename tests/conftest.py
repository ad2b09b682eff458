"""Fixtures every test folder shares: torch's thread count, a tiny model built once per session, JSONL files.

- Workers: the suite runs under pytest-xdist, one worker per core, each with one torch thread (`WORKERS`; a
  single process, `-n 0`, keeps torch's default).
- `_restore_torch_threads` (automatic): runs here use run.threads=1 (light on shared CPUs) and some tests set
  threads themselves; every test gives the next one its thread count back.
- `one_thread` (module scope; `pytestmark = pytest.mark.usefixtures("one_thread")`): one intra-op thread for a
  module's correctness tests (a 2-thread OpenMP team crawls when the cores are shared with other processes).
- `tiny_lm(task, vocab_size=, max_length=, **bootstrap_options)`: the directory of a random-init `tiny` preset
  with a tokenizer trained on the task's corpus, built once per session and settings (read-only: runs write
  their own directories).
- `tiny_rm(task, ...)`: a "reward model" made from that tiny model (its transformer under a one-output head with
  visible outputs, seeded), saved with the tokenizer; built once per session and settings.
- `write_jsonl(path, rows)`: rows as a JSONL file; returns the path.
- `perturbed_sampler(generate, sigma)`: a rollout `generate` whose recorded log-probs are off by N(0, sigma^2)
  per token (seeded): a sampler that is not the trainer, for the rollout-correction tests.
- `_drop_run_weights` (automatic): a passed test's checkpoints and model weights under its tmp_path are deleted.
- `cuda` (tests marked `cuda`): skipped, naming why, where torch sees no CUDA GPU (`pytest_runtest_setup`); on a
  GPU machine they run like the rest (each xdist worker that touches the GPU makes its own CUDA context, ~0.5 GB).
- `learning` (tests marked `learning`): the seed and thread count of a run whose result is a learned number,
  and `learning.above(name, value, bound)` / `learning.below(...)` to assert it. The defaults (seed 0, the
  thread count each test pins) are what CI runs; POSTTRAIN_TEST_SEED / POSTTRAIN_TEST_THREADS change them, and with
  POSTTRAIN_MARGINS=FILE every check is appended to FILE, so `scripts/test_margins.py` can measure each
  bound's margin over several seeds and both thread counts (RESULTS.md, "Test margins"). A bound must hold
  with room at every seed and thread count measured there, not only at the one CI happens to run.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import torch


# pytest-xdist (pyproject's `-n auto`) runs one worker per core side by side: each uses ONE torch thread, here and in
# every process a test starts (two 2-thread OpenMP teams on two cores run at a tenth of their speed).
WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if WORKERS > 1:
    os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


def pytest_collection_modifyitems(config, items):
    """Long modules first: the real tier, then modules with `slow` tests, then the rest (each group, and each
    module, in collection order). pytest-xdist hands modules out in this order (--dist loadscope), so a long
    module no longer starts last and runs alone while the other worker idles."""
    def module(item):
        return item.nodeid.split("::")[0]

    rank: dict[str, int] = {}
    for item in items:
        r = 0 if item.get_closest_marker("real") else 1 if item.get_closest_marker("slow") else 2
        rank[module(item)] = min(rank.get(module(item), 2), r)
    items.sort(key=lambda item: rank[module(item)])  # stable: a module's tests stay together, in order


def pytest_runtest_setup(item):
    """Tests marked `cuda` skip where there is no CUDA GPU."""
    if item.get_closest_marker("cuda") and not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU (marked cuda): torch.cuda.is_available() is False here")


TEST_SEED = int(os.environ.get("POSTTRAIN_TEST_SEED", "0"))
TEST_THREADS = int(os.environ["POSTTRAIN_TEST_THREADS"]) if os.environ.get("POSTTRAIN_TEST_THREADS") else None


@dataclass
class Learning:
    test: str
    seed: int = TEST_SEED
    threads: int | None = TEST_THREADS  # None: the thread count the test pins itself
    checks: list = field(default_factory=list)

    @property
    def overrides(self) -> list[str]:
        """Stage seed, model-init seed and (when set) thread count of the run: after a test's own options."""
        return [f"seed={self.seed}", f"model.seed={self.seed}"] + \
            ([f"run.threads={self.threads}"] if self.threads else [])

    def above(self, name: str, value: float, bound: float, context=None) -> None:
        self._check(name, float(value), ">", float(bound), float(value) - float(bound), context)

    def below(self, name: str, value: float, bound: float, context=None) -> None:
        self._check(name, float(value), "<", float(bound), float(bound) - float(value), context)

    def _check(self, name, value, op, bound, margin, context):
        row = {"test": self.test, "check": name, "value": value, "op": op, "bound": bound, "margin": margin,
               "seed": self.seed, "threads": self.threads}
        if os.environ.get("POSTTRAIN_MARGINS"):
            with open(os.environ["POSTTRAIN_MARGINS"], "a") as f:
                f.write(json.dumps(row) + "\n")
        assert margin > 0, f"{name} = {value:.4g}, must be {op} {bound:.4g} (seed {self.seed}, " \
                           f"{self.threads} threads): {context if context is not None else ''}"


@pytest.fixture
def learning(request):
    assert request.node.get_closest_marker("learning"), "tests that use `learning` are marked learning"
    return Learning(request.node.nodeid)


@pytest.fixture(autouse=True)
def _restore_torch_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


_PASSED = pytest.StashKey[bool]()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    report = yield
    if call.when == "call":
        item.stash[_PASSED] = report.passed
    return report


@pytest.fixture(autouse=True)
def _drop_run_weights(request):
    """Once a test has passed, the checkpoints and model weights its runs wrote under its tmp_path go (pytest keeps
    every tmp_path of its last three sessions; a run of the suite left ~4.5 GB on one worker, 60% of it
    checkpoints). The rest stays: a later test may still import a verifier module written there. A failed test
    keeps everything."""
    tmp = request.getfixturevalue("tmp_path") if "tmp_path" in request.fixturenames else None
    yield
    if tmp is not None and request.node.stash.get(_PASSED, False):
        import shutil

        for d in list(tmp.rglob("checkpoints")):
            shutil.rmtree(d, ignore_errors=True)
        for f in tmp.rglob("*.safetensors"):
            f.unlink(missing_ok=True)


@pytest.fixture(scope="module")
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def tiny_lm(tmp_path_factory):
    built: dict[tuple, Path] = {}

    def build(task: str = "tiny-summarize", *, vocab_size: int = 384, max_length: int = 256, **options) -> Path:
        key = (task, vocab_size, max_length, tuple(sorted(options.items())))
        if key not in built:
            from posttrain import tasks
            from posttrain.models import bootstrap

            out = tmp_path_factory.mktemp("tiny-lm") / "model"
            bootstrap("tiny", tasks.get_task(task).corpus(200, 0), out, vocab_size=vocab_size, seed=TEST_SEED,
                      max_length=max_length, **options)
            built[key] = out
        return built[key]

    return build


@pytest.fixture(scope="session")
def tiny_rm(tmp_path_factory, tiny_lm):
    built: dict[tuple, Path] = {}

    def build(task: str = "tiny-summarize", *, vocab_size: int = 384, max_length: int = 256, std: float = 0.5,
              seed: int = 1) -> Path:
        key = (task, vocab_size, max_length, std, seed)
        if key not in built:
            from transformers import AutoModelForSequenceClassification

            from posttrain.models import load_tokenizer

            lm = tiny_lm(task, vocab_size=vocab_size, max_length=max_length)
            tok = load_tokenizer(lm)
            torch.manual_seed(seed + TEST_SEED)
            rm = AutoModelForSequenceClassification.from_pretrained(str(lm), num_labels=1)
            rm.config.pad_token_id = tok.pad_token_id
            torch.nn.init.normal_(rm.score.weight, std=std)  # a head with visible outputs
            out = tmp_path_factory.mktemp("tiny-rm") / "rm"
            rm.save_pretrained(out)
            tok.save_pretrained(out)
            built[key] = out
        return built[key]

    return build


def _write_jsonl(path: Path, rows: list[dict]) -> Path:
    path = Path(path)
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


@pytest.fixture(scope="session")
def write_jsonl():
    return _write_jsonl


def _perturbed_sampler(generate, sigma: float, seed: int = 11):
    def perturbed(*args, **kwargs):
        out = generate(*args, **kwargs)
        g = torch.Generator().manual_seed(seed)
        for r in out:
            noise = (sigma * torch.randn(len(r.logprobs), generator=g)).tolist()
            r.logprobs = [a + b for a, b in zip(r.logprobs, noise)]
            r.policy_logprobs = [a + b for a, b in zip(r.policy_logprobs, noise)]
        return out
    return perturbed


@pytest.fixture(scope="session")
def perturbed_sampler():
    return _perturbed_sampler
