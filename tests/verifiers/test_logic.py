"""Tests for posttrain.verifiers.logic: generators (determinism, splits, difficulty, uniqueness) and exact checkers."""
from __future__ import annotations

import json
import random
import subprocess
import sys
from collections import Counter

import pytest

from posttrain.verifiers.base import AuditProblem
from posttrain.verifiers.logic import (FAMILIES, CountdownVerifier, KnightsKnavesVerifier, LogicVerifier, SudokuVerifier,
                             generate)
from posttrain.verifiers.puzzles import countdown, knights, sudoku

LOGIC = LogicVerifier()
LEVELS = {"countdown": countdown.DIFFICULTIES, "knights_knaves": knights.DIFFICULTIES, "sudoku": sudoku.DIFFICULTIES}


def _key(item: dict) -> str:
    ref = dict(item["reference"])
    ref.pop("split", None)
    ref.pop("difficulty", None)
    return json.dumps(ref, sort_keys=True)


# ------------------------------------------------------------------ generators
@pytest.mark.parametrize("family", list(FAMILIES))
def test_generate_is_deterministic_and_seeded(family):
    a = generate(family, 20, seed=7, split="train")
    assert a == generate(family, 20, seed=7, split="train")
    assert a != generate(family, 20, seed=8, split="train")
    assert generate(family, 5, seed=7) == a[:5]  # a smaller batch is a prefix of a larger one
    for item in a:
        assert set(item) == {"prompt", "reference", "gold"}
        assert item["reference"]["family"] == family
        json.dumps(item["reference"])  # JSON-serialisable
        assert "<answer></answer>" in item["prompt"]  # the format is stated, and an echoed prompt answers nothing


@pytest.mark.parametrize("family", list(FAMILIES))
def test_every_gold_scores_one_at_every_difficulty_and_split(family):
    verifier = FAMILIES[family]()
    for split in ("train", "test"):
        for level in LEVELS[family]:
            items = generate(family, 25, seed=level, split=split, difficulty=level)
            assert len({_key(x) for x in items}) == 25  # distinct within a batch
            for item in items:
                v = verifier.check(item["gold"], item["reference"])
                assert v.score == 1.0 and v.reason == "correct", (item, v)
                assert LOGIC.check(item["gold"], item["reference"]).passed


@pytest.mark.parametrize("family", list(FAMILIES))
def test_splits_are_disjoint(family):
    train = generate(family, 150, seed=0, split="train")
    test = generate(family, 60, seed=0, split="test")
    assert not {_key(x) for x in train} & {_key(x) for x in test}
    if family == "countdown":
        assert max(max(x["reference"]["numbers"]) for x in train) <= 50
        assert all(max(x["reference"]["numbers"]) > 50 for x in test)
    elif family == "knights_knaves":
        assert not {n for x in train for n in x["reference"]["names"]} & {n for x in test for n in x["reference"]["names"]}
    else:
        assert not {x["reference"]["solution"] for x in train} & {x["reference"]["solution"] for x in test}


def test_difficulty_knob():
    for level in countdown.DIFFICULTIES:
        assert all(len(x["reference"]["numbers"]) == level + 2 for x in generate("countdown", 10, difficulty=level))
    for level in knights.DIFFICULTIES:
        assert all(len(x["reference"]["names"]) == level + 1 for x in generate("knights_knaves", 10, difficulty=level))
    for level in sudoku.DIFFICULTIES:
        puzzles = [x["reference"]["puzzle"] for x in generate("sudoku", 10, difficulty=level)]
        assert all(16 - p.count(".") == sudoku.GIVENS[level] for p in puzzles)
    with pytest.raises(ValueError):
        generate("sudoku", 3, difficulty=9)
    with pytest.raises(ValueError):
        generate("countdown", 3, split="validation")
    with pytest.raises(ValueError):
        generate("chess", 3)


def test_puzzles_have_unique_solutions():
    for item in generate("knights_knaves", 60, seed=3, difficulty=4):
        ref = item["reference"]
        found = knights.models(len(ref["names"]), ref["statements"])
        assert found == [tuple(ref["solution"][n] == "knight" for n in ref["names"])]
    for item in generate("sudoku", 60, seed=3, difficulty=4):
        puzzle = [0 if ch == "." else int(ch) for ch in item["reference"]["puzzle"]]
        assert ["".join(map(str, s)) for s in sudoku.solutions(puzzle, limit=5)] == [item["reference"]["solution"]]
    assert len(sudoku.all_grids()) == 288


@pytest.mark.parametrize("family", list(FAMILIES))
def test_no_gold_solves_another_problem_of_its_batch(family):
    items = generate(family, 40, seed=11)
    verifier = FAMILIES[family]()
    for i, a in enumerate(items):
        for j, b in enumerate(items):
            if i != j:
                assert verifier.check(a["gold"], b["reference"]).score == 0.0


def test_logic_verifier_mixes_and_dispatches():
    items = LogicVerifier.generate(9, seed=2)
    assert [x["reference"]["family"] for x in items] == list(FAMILIES) * 3
    problems = LOGIC.audit_problems(6, seed=1)
    assert all(isinstance(p, AuditProblem) and LOGIC.check(p.gold, p.reference).passed for p in problems)
    v = LOGIC.check(problems[0].gold, problems[0].reference)
    assert v.details["family"] == problems[0].reference["family"]
    assert len(LogicVerifier.generate(3, difficulty=5)) == 3  # clamped per family
    for bad in ({"numbers": [1], "target": 1}, {"family": "chess"}, "countdown"):
        with pytest.raises(ValueError):
            LOGIC.check("<answer>1</answer>", bad)


# ------------------------------------------------------------------ hostile and malformed answers
@pytest.mark.parametrize("family", list(FAMILIES))
def test_adversarial_cases_score_as_stated(family):
    verifier = FAMILIES[family]()
    for problem in verifier.audit_problems(15, seed=4):
        cases = verifier.adversarial_cases(problem)
        assert len(cases) >= 8
        assert sum(1 for _, _, expected in cases if expected == 0.0) >= 8
        for label, completion, expected in cases:
            v = verifier.check(completion, problem.reference)
            assert v.score == expected, (label, completion, v)
            assert (v.reason == "correct") == (expected == 1.0)
            json.dumps(v.to_dict())
        assert LOGIC.adversarial_cases(problem) == cases


@pytest.mark.parametrize("family", list(FAMILIES))
def test_generic_bad_outputs(family):
    verifier = FAMILIES[family]()
    item = generate(family, 1, seed=5)[0]
    rng = random.Random(0)
    junk = ["", "   \n", item["prompt"], "<answer></answer>", "I don't know.", "\\boxed{}", "<answer>" * 50,
            "".join(rng.choice("0123456789 ()+-*/=\n.:|knightave") for _ in range(5000)),
            "x" * 1_000_000, (item["gold"] + "\n") * 3 + "<answer>nonsense</answer>"]
    for completion in junk:
        v = verifier.check(completion, item["reference"])
        assert v.score == 0.0, (completion[:100], v)
    for _ in range(300):  # fuzz: never raises, always 0 or 1
        text = "".join(rng.choice("0123456789 ()+-*/=\n.:|,;ABCabcknightsave<>/answer") for _ in range(rng.randint(0, 80)))
        assert verifier.check(text, item["reference"]).score in (0.0, 1.0)


# ------------------------------------------------------------------ countdown
CD = {"family": "countdown", "numbers": [3, 5, 2, 7, 7], "target": 16}


@pytest.mark.parametrize("completion", [
    "<answer>(3 + 5) * 2</answer>", "<answer>(3+5)*2 = 16</answer>", "<answer>16 = (3 + 5) × 2</answer>",
    "<answer>**(3+5)*2**</answer>", "<answer>Expression: (3 + 5) * 2</answer>", "\\boxed{(3+5) \\cdot 2}",
    "So the answer is $(3+5) \\times 2 = 16$.", "(3+5)*2 = 8*2 = 16", "<answer>7 + 7 + 2</answer>",
    "<answer>(3 + 5)x2</answer>", "<answer>\\frac{(3 + 5) * 2 * 7}{7}</answer>", "Let me try.\n3 + 5 = 8\n(3 + 5) * 2",
    "<answer>7 / 7 + 5 * 3</answer>",
])
def test_countdown_accepts(completion):
    assert CountdownVerifier().check(completion, CD).reason == "correct"


@pytest.mark.parametrize("completion, reason", [
    ("<answer>3 * 3 + 7</answer>", "uses 3 2 times but it is given 1 time(s)"),
    ("<answer>4 * 4</answer>", "uses 4, which is not among the numbers"),
    ("<answer>abs(-16)</answer>", "function call not allowed"),
    ("<answer>(16).real</answer>", "attribute access not allowed"),
    ("<answer>9**9**9</answer>", "operator ** not allowed"),
    ("<answer>2 ** 4</answer>", "operator ** not allowed"),
    ("<answer>-(3 - 5) * 7</answer>", "unary operator not allowed"),
    ("<answer>(3 + 5) * 2.0</answer>", "literal 2.0 not allowed (integers only)"),
    ("<answer>3 / (7 - 7)</answer>", "division by zero"),
    ("<answer>3 + 5 * 2</answer>", "evaluates to 13, not 16"),
    ("<answer>3 + 5 * 2 = 16</answer>", "claims 16 but the expression equals 13"),
    ("<answer>(3 + 5) * 2 = 17</answer>", "claims 17 but the expression equals 16"),
    ("<answer>16</answer>", "a bare number is not an expression"),
    ("<answer>(3 + 5) * 2; 1</answer>", "unparseable expression"),
    ("<answer>" + "(" * 220 + "3" + ")" * 220 + "</answer>", "unparseable expression"),
    ("<answer>" + "+".join(["1"] * 300) + "</answer>", "expression too long"),
    ("<answer>x</answer>", "name not allowed"),
    ("<answer>3 // 2</answer>", "operator // not allowed"),
    ("I could not find it.", "no answer found"),
])
def test_countdown_rejects(completion, reason):
    v = CountdownVerifier().check(completion, CD)
    assert v.score == 0.0 and v.reason == reason


def test_countdown_exact_arithmetic():
    ref = {"family": "countdown", "numbers": [1, 3, 4, 6], "target": 24}
    assert CountdownVerifier().check("<answer>6 / (1 - 3 / 4)</answer>", ref).passed  # needs 1/4 exactly
    assert countdown.eval_safe("1 / 3 + 1 / 6") == countdown.Fraction(1, 2)
    with pytest.raises(ValueError):
        countdown.eval_safe("__import__('os')")


# ------------------------------------------------------------------ knights and knaves
KK = {"family": "knights_knaves", "names": ["Alice", "Bob", "Carol"],
      "solution": {"Alice": "knight", "Bob": "knave", "Carol": "knight"}}


@pytest.mark.parametrize("completion", [
    "<answer>Alice is a knight, Bob is a knave, Carol is a knight</answer>",
    "<answer>alice: Knight; BOB: knave; carol: KNIGHT</answer>",
    "<answer>Alice is a knight and Bob is a knave and Carol is a knight</answer>",
    "<answer>Carol is a knight. Bob is a knave. Alice is a knight.</answer>",
    "<answer>Alice and Carol are knights, Bob is a knave</answer>",
    "<answer>Alice, Carol: knights. Bob: knave</answer>",
    "<answer>Knights: Alice, Carol\nKnaves: Bob</answer>",
    "<answer>The knights are Alice and Carol; the knave is Bob.</answer>",
    "<answer>- **Alice**: knight\n- **Bob**: knave\n- **Carol**: knight</answer>",
    "<answer>Bob is not a knight, Alice is not a knave, Carol is a knight</answer>",
    "<answer>Alice (knight), Bob (knave), Carol (knight)</answer>",
    "\\boxed{\\text{Alice: knight, Bob: knave, Carol: knight}}",
    "Suppose Alice is a knave; then Bob is a knight, a contradiction.\n\nSo Alice is a knight, Bob is a knave, and Carol is a knight.",
    "Either Alice lies or not...\n\nFinal answer: Alice - knight, Bob - knave, Carol - knight",
])
def test_knights_accepts(completion):
    assert KnightsKnavesVerifier().check(completion, KK).reason == "correct"


@pytest.mark.parametrize("completion, reason", [
    ("<answer>Alice is a knight, Bob is a knave</answer>", "unassigned: Carol"),
    ("<answer>Alice is a knight, Bob is a knave, Carol is a knight, Alice is a knave</answer>",
     "contradictory: Alice called both knight and knave"),
    ("<answer>Alice is a knight or a knave, Bob is a knave, Carol is a knight</answer>", "hedged answer"),
    ("<answer>Alice is a knight, Bob is a knave, Carol is either</answer>", "hedged answer"),
    ("<answer>Alice is a knight, Bob is a knave, Carol is a knave</answer>", "wrong: Carol"),
    ("<answer>Alice is a knight, Bob is a knave, Carol is a knight, Zed is a knight</answer>",
     "assigns Zed, who is not in the puzzle"),
    ("<answer>Alice, Bob, Carol</answer>", "no answer found"),
    ("No idea.", "no answer found"),
])
def test_knights_rejects(completion, reason):
    v = KnightsKnavesVerifier().check(completion, KK)
    assert v.score == 0.0 and v.reason == reason


def test_knights_single_letter_names_are_case_sensitive():
    ref = {"family": "knights_knaves", "names": ["A", "B"], "solution": {"A": "knight", "B": "knave"}}
    v = KnightsKnavesVerifier()
    assert v.check("<answer>A is a knight, B is a knave</answer>", ref).passed
    assert v.check("<answer>B: knave, A: knight</answer>", ref).passed
    assert not v.check("<answer>B is a knave and a knight is A</answer>", ref).passed


# ------------------------------------------------------------------ knights and knaves: other role words
SAINTS = {"family": "knights_knaves", "names": ["Alice", "Bob", "Carol"], "roles": ["saint", "sinner"],
          "solution": {"Alice": "saint", "Bob": "sinner", "Carol": "saint"}}
KK_DATASET = {"names": ["Zoey", "Oliver"], "solution": [True, False], "statements": "(('lying', 1),)",
              "knight_knave": {"knight": "hero", "knave": "villain", "a_knight": "a hero", "a_knave": "a villain",
                               "Knight": "Hero", "Knave": "Villain"}}
FROM_PROMPT = {"names": ["Alice", "Bob", "Carol"], "solution": {"Alice": "knight", "Bob": "knave", "Carol": "knight"},
               "prompt": "A very special island is inhabited only by altruists and egoists. Altruists always tell "
                         "the truth, and egoists always lie. Alice says ..."}
FROM_SOLUTION = {"names": ["Alice", "Bob", "Carol"], "solution": {"Alice": "Angel", "Bob": "devils", "Carol": "angel"}}
TRUTH_TELLERS = {"names": ["Alice", "Bob", "Carol"], "roles": ["truth-teller", "liar"],
                 "solution": {"Alice": "truth-teller", "Bob": "liar", "Carol": "truth-teller"}}
FLIPPED = {"names": ["Zoey", "Oliver"], "solution": [True, False], "knight_knave": {"knight": "knave", "knave": "knight"}}


@pytest.mark.parametrize("reference,completion", [
    pytest.param(SAINTS, "<answer>Alice is a saint, Bob is a sinner, Carol is a saint</answer>", id="own-words"),
    pytest.param(SAINTS, "<answer>Saints: Alice, Carol. Sinners: Bob</answer>", id="plural-capitalised-list"),
    pytest.param(SAINTS, "<answer>Alice and Carol are SAINTS; Bob is a Sinner.</answer>", id="group-upper-case"),
    pytest.param(SAINTS, "<answer>Alice is a knight, Bob is a knave, Carol is a knight</answer>", id="standard-words"),
    pytest.param(SAINTS, "<answer>Alice is a saint, Bob is a knave, Carol is a knight</answer>", id="mixed-forms"),
    pytest.param(SAINTS, "<answer>Alice tells the truth, Bob lies, Carol tells the truth</answer>", id="verbs"),
    pytest.param(SAINTS, "So, in the end, Alice is a saint, Bob is a sinner and Carol is a saint.", id="free-text"),
    pytest.param(KK_DATASET, "CONCLUSION:\n(1) Zoey is a hero\n(2) Oliver is a villain", id="kk-dataset-format"),
    pytest.param(KK_DATASET, "<answer>Heroes: Zoey; villains: Oliver</answer>", id="kk-irregular-plural"),
    pytest.param(FROM_PROMPT, "<answer>Alice and Carol are altruists, Bob is an egoist</answer>", id="roles-from-prompt"),
    pytest.param(FROM_SOLUTION, "<answer>Alice and Carol are angels, Bob is a devil</answer>", id="roles-from-solution"),
    pytest.param(TRUTH_TELLERS, "<answer>Alice is a truth teller, Bob is a liar, Carol is a truthteller</answer>",
                 id="truth-teller-spellings"),
    pytest.param(TRUTH_TELLERS, "<answer>Truth-tellers: Alice and Carol. Liars: Bob.</answer>", id="truth-tellers-plural"),
    pytest.param(FLIPPED, "<answer>Zoey is a knave, Oliver is a knight</answer>", id="swapped-words-read-as-the-puzzle-says"),
    pytest.param(FLIPPED, "<answer>Zoey is a truth-teller, Oliver is a liar</answer>", id="swapped-words-descriptive"),
])
def test_knights_reads_the_puzzles_role_words(reference, completion):
    v = KnightsKnavesVerifier().check(completion, reference)
    assert v.reason == "correct", v


@pytest.mark.parametrize("reference,completion,reason", [
    pytest.param(SAINTS, "<answer>Alice is a saint, Bob is a sinner, Carol is a sinner</answer>", "wrong: Carol", id="wrong"),
    pytest.param(SAINTS, "<answer>Alice is a sinner, Bob is a saint, Carol is a sinner</answer>", "wrong: Alice, Bob, Carol",
                 id="all-wrong"),
    pytest.param(SAINTS, "<answer>Alice is an angel, Bob is a devil, Carol is an angel</answer>",
                 "uses role words not in this puzzle (angel, devil; the puzzle's are saint/sinner)", id="another-pair"),
    pytest.param(SAINTS, "<answer>Alice is a saint, Bob is a devil, Carol is a saint</answer>",
                 "uses role words not in this puzzle (devil; the puzzle's are saint/sinner)", id="one-word-of-another-pair"),
    pytest.param(SAINTS, "<answer>Alice is a saint or a sinner, Bob is a sinner, Carol is a saint</answer>", "hedged answer",
                 id="hedge"),
    pytest.param(SAINTS, "<answer>Alice is a saint and a knave, Bob is a sinner, Carol is a saint</answer>",
                 "contradictory: Alice called both saint and sinner", id="two-forms-contradict"),
    pytest.param(SAINTS, "<answer>Alice is a saint, Bob is a sinner</answer>", "unassigned: Carol", id="unassigned"),
    pytest.param(SAINTS, "<answer>Alice is a saint, Bob is a sinner, Carol is a saint, Zed is a saint</answer>",
                 "assigns Zed, who is not in the puzzle", id="stranger"),
    pytest.param(FLIPPED, "<answer>Zoey is a knight, Oliver is a knave</answer>", "wrong: Zoey, Oliver",
                 id="standard-reading-of-swapped-words"),
    pytest.param(FLIPPED, "<answer>Zoey is a knave (a liar), Oliver is a knight</answer>",
                 "contradictory: Zoey called both knave and knight", id="swapped-words-mixed-ambiguously"),
    pytest.param(KK_DATASET, "<answer>Zoey is a saint, Oliver is a sinner</answer>",
                 "uses role words not in this puzzle (saint, sinner; the puzzle's are hero/villain)", id="kk-other-pair"),
    pytest.param(KK, "<answer>Alice is a saint, Bob is a sinner, Carol is a saint</answer>",
                 "uses role words not in this puzzle (saint, sinner; the puzzle's are knight/knave)", id="default-puzzle-other-pair"),
])
def test_knights_rejects_wrong_role_words(reference, completion, reason):
    v = KnightsKnavesVerifier().check(completion, reference)
    assert (v.score, v.reason) == (0.0, reason)


def test_knights_role_words_in_the_default_puzzle():
    v = KnightsKnavesVerifier()
    assert v.check("<answer>Alice is a truth-teller, Bob is a liar, Carol is a truth-teller</answer>", KK).passed
    assert v.check("<answer>KNIGHTS: Alice, Carol; KNAVES: Bob</answer>", KK).passed


def test_knights_generate_with_roles():
    items = knights.generate(8, seed=1, roles=("hero", "villain"))
    plain = knights.generate(8, seed=1)
    assert [x["reference"]["statements"] for x in items] == [x["reference"]["statements"] for x in plain]
    assert "roles" not in plain[0]["reference"] and "knight" in plain[0]["prompt"]
    for item in items:
        ref = item["reference"]
        assert ref["roles"] == ["hero", "villain"] and set(ref["solution"].values()) <= {"hero", "villain"}
        assert "knight" not in item["prompt"] and "a hero, who always tells the truth" in item["prompt"]
        assert KnightsKnavesVerifier().check(item["gold"], ref).passed
        assert LOGIC.check(item["gold"], ref).passed
        swapped = item["gold"].replace("villain", "@").replace("hero", "villain").replace("@", "hero")
        assert not KnightsKnavesVerifier().check(swapped, ref).passed
    flipped = knights.retheme(plain[0], ("knave", "knight"))
    assert flipped["reference"]["roles"] == ["knave", "knight"]
    assert KnightsKnavesVerifier().check(flipped["gold"], flipped["reference"]).passed
    assert not KnightsKnavesVerifier().check(plain[0]["gold"], flipped["reference"]).passed
    with pytest.raises(ValueError):
        knights.generate(2, roles=("saint", "saint"))


def test_knights_role_reference_validation():
    v = KnightsKnavesVerifier()
    with pytest.raises(ValueError):
        v.check("x", dict(SAINTS, roles=["saint"]))
    with pytest.raises(ValueError):  # a value that is neither the puzzle's words nor knight/knave
        v.check("x", dict(SAINTS, solution={"Alice": "saint", "Bob": "angel", "Carol": "saint"}))
    with pytest.raises(ValueError):
        v.check("x", dict(KK_DATASET, solution=[True]))


def test_knights_reference_validation():
    v = KnightsKnavesVerifier()
    with pytest.raises(ValueError):
        v.check("x", {"names": ["A", "A"], "solution": {"A": "knight"}})
    with pytest.raises(ValueError):
        v.check("x", {"names": ["A", "B"], "solution": {"A": "knight"}})
    with pytest.raises(ValueError):  # two models: the statements do not pin the solution down
        v.check("x", {"names": ["A", "B"], "solution": {"A": "knight", "B": "knight"},
                      "statements": [[0, ["is", 1, True]], [1, ["is", 0, True]]]})
    with pytest.raises(ValueError):  # the given solution is not a model
        v.check("x", {"names": ["A", "B"], "solution": {"A": "knight", "B": "knight"},
                      "statements": [[0, ["is", 1, False]], [1, ["is", 0, True]]]})


# ------------------------------------------------------------------ sudoku
SD = {"family": "sudoku", "puzzle": "3.211...2.1.4.3.", "solution": "3421124323144132"}


@pytest.mark.parametrize("completion", [
    "<answer>\n3421\n1243\n2314\n4132\n</answer>",
    "<answer>3 4 2 1\n1 2 4 3\n2 3 1 4\n4 1 3 2</answer>",
    "<answer>3 4 | 2 1\n1 2 | 4 3\n----+----\n2 3 | 1 4\n4 1 | 3 2</answer>",
    "<answer>3421124323144132</answer>",
    "<answer>[[3,4,2,1],[1,2,4,3],[2,3,1,4],[4,1,3,2]]</answer>",
    "<answer>Row 1: 3 4 2 1\nRow 2: 1 2 4 3\nRow 3: 2 3 1 4\nRow 4: 4 1 3 2</answer>",
    "Working:\n3 . 2 1\n1 . . .\n\nFinal grid:\n```\n3421\n1243\n2314\n4132\n```",
    "\\boxed{3421124323144132}",
])
def test_sudoku_accepts(completion):
    assert SudokuVerifier().check(completion, SD).reason == "correct"


@pytest.mark.parametrize("completion, reason", [
    ("<answer>\n3.21\n1243\n2314\n4132\n</answer>", "incomplete grid"),
    ("<answer>\n4312\n2134\n3241\n1423\n</answer>", "changes the given 3 at row 1, column 1"),
    ("<answer>\n3412\n1243\n2314\n4132\n</answer>", "changes the given 2 at row 1, column 3"),
    ("<answer>\n3421\n1243\n2314\n4135\n</answer>", "digit out of range"),
    ("<answer>\n3421\n1243\n2314\n</answer>", "not a 4x4 grid"),
    ("<answer>\n3421\n1243\n2314\n4132\n\n3421\n1243\n2314\n4132\n</answer>", "several grids"),
    ("<answer>\n34211\n12431\n23141\n41321\n</answer>", "not a 4x4 grid"),
    ("<answer>no idea</answer>", "no grid found"),
])
def test_sudoku_rejects(completion, reason):
    v = SudokuVerifier().check(completion, SD)
    assert v.score == 0.0 and v.reason == reason


def test_sudoku_rule_violation_reason():
    ref = {"family": "sudoku", "puzzle": "1..............."}  # not unique
    with pytest.raises(ValueError):
        SudokuVerifier().check("<answer>1234123412341234</answer>", ref)
    v = SudokuVerifier().check("<answer>3421124323144132</answer>".replace("3421", "3412", 1), SD)
    assert v.score == 0.0 and v.reason.startswith("changes the given")
    assert sudoku.first_problem([1, 2, 3, 4] * 4) == "column 1 repeats 1"


# ------------------------------------------------------------------ layering
def test_imports_without_torch_or_posttrain():
    code = ("import sys, posttrain.verifiers.logic, posttrain.verifiers.code_sandbox\n"
            "bad = [m for m in sys.modules if m.split('.')[0] in ('torch', 'numpy', 'transformers')\n"
            "       or (m.startswith('posttrain.') and not m.startswith('posttrain.verifiers'))]\n"
            "assert not bad, bad\n")
    subprocess.run([sys.executable, "-c", code], check=True)
    assert Counter(x["reference"]["family"] for x in LogicVerifier.generate(6)) == {f: 2 for f in FAMILIES}
