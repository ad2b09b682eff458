"""`loop.stream_seed`: every stream of randomness a trainer draws from is named, stable across processes and
machines, and no two streams share a seed; the trainers derive no seed by hand."""
from __future__ import annotations

import ast
import itertools
import os
import subprocess
import sys
from pathlib import Path

import pytest

from posttrain.loop import stream_seed

ROOT = Path(__file__).resolve().parents[2]
TRAINERS = sorted((ROOT / "posttrain" / "trainers").glob("*.py"))

# The streams the trainers draw from (`test_every_purpose_in_the_trainers_is_listed_here` keeps it in step).
PURPOSES = ["grpo/sample", "grpo/resample-batch", "grpo/curriculum", "grpo/minibatch",
            "ppo/reward-norm", "distill/mix", "distill/sample", "dpo/online-prompts",
            "dpo/online-sample", "dpo/online-batch", "eval/sample"]


def test_stream_seed_is_a_63_bit_pure_function_of_its_arguments():
    a = stream_seed(3, "grpo/sample", 5, 1)
    assert a == stream_seed(3, "grpo/sample", 5, 1)
    assert 0 <= a < 2 ** 63
    assert len({a, stream_seed(4, "grpo/sample", 5, 1), stream_seed(3, "grpo/sample", 1, 5),
                stream_seed(3, "grpo/sample", 5), stream_seed(3, "grpo/sample", 5, 1, 0)}) == 5
    with pytest.raises(ValueError):
        stream_seed(0, "", 1)
    with pytest.raises(ValueError):
        stream_seed(0, "grpo/sample", 1.0)


def test_stream_seed_is_the_same_in_another_process_whatever_its_hash_salt():
    """Not Python's salted `hash`: a fresh interpreter with another PYTHONHASHSEED derives the same seeds."""
    here = [stream_seed(s, p, 7, 2) for s in (0, 1, 12345) for p in PURPOSES]
    code = ("from posttrain.loop import stream_seed; import sys; P = sys.argv[1].split(',');"
            "print([stream_seed(s, p, 7, 2) for s in (0, 1, 12345) for p in P])")
    for salt in ("1", "2"):
        out = subprocess.run([sys.executable, "-c", code, ",".join(PURPOSES)], capture_output=True, text=True,
                             check=True, env={**os.environ, "PYTHONHASHSEED": salt}, cwd=ROOT)
        assert out.stdout.strip() == str(here)


def test_two_purposes_never_share_a_stream():
    """Over a realistic grid of seeds, steps, rounds / passes: all seeds distinct, across purposes and indices, and
    none equal to a small raw seed (the data order `loop.batch_indices(..., seed, step)` uses the run's own)."""
    seen: dict[int, tuple] = {}
    for seed, purpose in itertools.product(range(4), PURPOSES):
        grid = [()] + [(i,) for i in range(400)] + [(step, r) for step in range(400) for r in range(4)]
        for idx in grid:
            s = stream_seed(seed, purpose, *idx)
            assert s not in seen, f"{(seed, purpose, idx)} and {seen[s]} share seed {s}"
            seen[s] = (seed, purpose, idx)
    assert min(seen) > 2 ** 32


def _derived_seed_arithmetic(tree: ast.AST) -> list[int]:
    """Lines of arithmetic on a seed (`cfg.seed * 1_000_003 + step`, `seed + 7`): the hand-made streams."""
    def names_seed(node: ast.AST) -> bool:
        return any((isinstance(n, ast.Name) and "seed" in n.id) or (isinstance(n, ast.Attribute) and "seed" in n.attr)
                   for n in ast.walk(node))

    return [node.lineno for node in ast.walk(tree)
            if isinstance(node, ast.BinOp) and (names_seed(node.left) or names_seed(node.right))]


def _seeded_without_the_helper(tree: ast.AST) -> list[int]:
    """Lines where a generator is seeded (random.Random, manual_seed, default_rng) by anything but `stream_seed`,
    or numpy's own hash of a list of integers (`default_rng([seed, it, epoch])`: PPO's epoch shuffles, kept as
    `loop.batch_indices` seeds its epochs; a SeedSequence of the list, not arithmetic on the seed)."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if name in ("Random", "manual_seed", "default_rng", "Generator") and node.args:
                arg = node.args[0]
                ok = isinstance(arg, ast.Call) and getattr(arg.func, "attr", getattr(arg.func, "id", "")) \
                    == "stream_seed" or (isinstance(arg, ast.Name) and arg.id == "seed") \
                    or (name == "default_rng" and isinstance(arg, ast.List))
                if not ok:
                    out.append(node.lineno)
    return out


# Streams kept at their values from before `loop.stream_seed` (each function says why): file -> function.
KEPT = {"ppo.py": "sample_seed"}


def _without_kept(tree: ast.Module, name: str) -> ast.Module:
    keep = KEPT.get(name)
    return ast.Module([n for n in tree.body if not (isinstance(n, ast.FunctionDef) and n.name == keep)], [])


@pytest.mark.parametrize("path", TRAINERS, ids=lambda p: p.name)
def test_trainers_derive_streams_only_through_the_helper(path):
    tree = _without_kept(ast.parse(path.read_text(), str(path)), path.name)
    assert _derived_seed_arithmetic(tree) == [], f"{path.name}: derive the seed with loop.stream_seed"
    assert _seeded_without_the_helper(tree) == [], f"{path.name}: seed generators with loop.stream_seed"


def test_the_static_checks_catch_the_old_formulas():
    old = ast.parse("a = cfg.seed * 1_000_003 + step\nb = cfg.seed + 7919 * rnd\n"
                    "g = torch.Generator().manual_seed(cfg.seed * 101)\nr = random.Random(f'online:{cfg.seed}')\n"
                    "n = np.random.default_rng(cfg.seed + it)\n")
    assert sorted(set(_derived_seed_arithmetic(old))) == [1, 2, 3, 5]
    assert _seeded_without_the_helper(old) == [3, 4, 5]


def test_every_purpose_in_the_trainers_is_listed_here():
    """The list above is the trainers' streams: a new one is named here too (and so in the collision test)."""
    used = set()
    for path in TRAINERS:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "stream_seed":
                assert isinstance(node.args[1], ast.Constant), f"{path.name}:{node.lineno}: a literal purpose"
                used.add(node.args[1].value)
    assert used == set(PURPOSES)
