"""Knights and knaves: knights always tell the truth, knaves always lie; who is which?

Reference: ``{"family": "knights_knaves", "names": [...], "solution": {name: "knight"|"knave"},
"statements": [[speaker_index, statement], ...]}`` (statements optional for checking; when
present the solution is verified to be their only model, else the reference raises).
Statements are JSON trees: ``["is", i, true]`` (i is a knight; false: a knave), ``["not", S]``,
``["and"|"or"|"imp"|"iff", S, T]``, ``["same"|"diff", i, j]``, ``["count", k, true]`` (exactly k
of the inhabitants are knights; false: knaves).

Answer: every inhabitant must be assigned, in any order, case-insensitively, in the forms
people write: "Alice is a knight, Bob is a knave", "Alice: knight; Bob: knave", "Alice is a
knight and Bob is a knave", "Alice and Carol are knights", "Knights: Alice, Carol",
"Bob is not a knight", markdown lists and bold. Scope: the ``<answer>`` tag / ``\\boxed{}``;
in free text, the text after the last "answer"/"conclusion"/"solution" marker, else the last
paragraph that assigns anyone. Scores 0: an inhabitant left out ("unassigned"), one called
both ("contradictory"), a hedge ("knight or knave", "either", "could be", "unknown"), an
assignment for someone not in the puzzle, a wrong assignment. Single-letter names ("A is a
knight") are matched case-sensitively, so the article "a" is never read as a name.

Generator: a random hidden assignment, one true-to-character statement per inhabitant (more
when needed), kept only when brute force over all 2^n assignments finds exactly one model.
Difficulty d (1-5): d + 1 inhabitants and richer statements. Split: "train" and "test" draw
names from disjoint lists, so they never share a puzzle. Within a batch no two puzzles have
the same inhabitants and solution, so one puzzle's gold never solves another.
"""
from __future__ import annotations

import itertools
import random
import re
from typing import Any

from verifiers.base import AuditProblem, Verdict
from verifiers.puzzles.common import (PuzzleVerifier, Split, check_generate_args, generate_unique, make_rng,
                                      require, strip_markup)

FAMILY = "knights_knaves"
DIFFICULTIES = range(1, 6)
TRAIN_NAMES = ("Alice", "Bob", "Carol", "Dave", "Eve", "Frank", "Gina", "Hank", "Ivy", "Jack", "Kara", "Liam",
               "Mona", "Nate", "Olga", "Paul", "Rita", "Sam", "Tina", "Uma")
TEST_NAMES = ("Aaron", "Bianca", "Cyrus", "Delia", "Emmett", "Fiona", "Gideon", "Hazel", "Isaac", "Juno", "Kiran",
              "Lena", "Marcus", "Nadia", "Oscar", "Priya", "Quentin", "Rosa", "Silas", "Tessa")
_KIND = {True: "knight", False: "knave"}
_NOT_NAMES = {"he", "she", "it", "this", "that", "each", "every", "everyone", "everybody", "someone", "somebody",
              "nobody", "one", "then", "so", "thus", "therefore", "hence", "who", "which", "anyone", "person",
              "speaker", "inhabitant", "the", "and", "but", "if", "also", "only", "exactly", "neither", "none"}
_HEDGE = re.compile(r"\bknights?\s*(?:or|/|and/or)\s*(?:an?\s+)?knaves?\b|\bknaves?\s*(?:or|/|and/or)\s*(?:an?\s+)?knights?\b"
                    r"|\beither\b|\bcould be\b|\bmight be\b|\bmay be\b|\bunknown\b|\bundetermined\b|\bunclear\b"
                    r"|\bcannot be determined\b|\bcan't be determined\b|\bnot determined\b", re.I)
_MARKER = re.compile(r"\b(?:final answer|answer|conclusion|solution)\b", re.I)


# ---------------------------------------------------------------------- statements
def evaluate(statement: list, world: tuple[bool, ...]) -> bool:
    """Truth of a statement tree in a world (world[i] is True when inhabitant i is a knight)."""
    op = statement[0]
    if op == "is":
        return world[statement[1]] == statement[2]
    if op == "not":
        return not evaluate(statement[1], world)
    if op in ("and", "or", "imp", "iff"):
        a, b = evaluate(statement[1], world), evaluate(statement[2], world)
        return {"and": a and b, "or": a or b, "imp": (not a) or b, "iff": a == b}[op]
    if op == "same":
        return world[statement[1]] == world[statement[2]]
    if op == "diff":
        return world[statement[1]] != world[statement[2]]
    if op == "count":
        return sum(1 for w in world if w == statement[2]) == statement[1]
    raise ValueError(f"knights reference: unknown statement operator {op!r}")


def models(n: int, statements: list) -> list[tuple[bool, ...]]:
    """Every assignment in which each speaker's statements are true exactly when the speaker is a knight."""
    return [w for w in itertools.product((True, False), repeat=n)
            if all(evaluate(s, w) == w[speaker] for speaker, s in statements)]


def render(statement: list, names: list[str], speaker: int) -> str:
    def who(i: int) -> str:
        return "I" if i == speaker else names[i]

    op = statement[0]
    if op == "is":
        i, knight = statement[1], statement[2]
        return f"{'I am' if i == speaker else names[i] + ' is'} a {_KIND[knight]}"
    if op == "not":
        inner = statement[1]
        both = "both " if inner[0] == "and" else ""  # "not (A and B)", never read as "(not A) and B"
        return f"it is not true that {both}{render(inner, names, speaker)}"
    if op in ("and", "or", "imp", "iff"):
        a, b = render(statement[1], names, speaker), render(statement[2], names, speaker)
        return {"and": f"{a} and {b}", "or": f"{a} or {b}", "imp": f"if {a}, then {b}",
                "iff": f"{a} if and only if {b}"}[op]
    if op in ("same", "diff"):
        i, j = statement[1], statement[2]
        pair = f"{who(j)} and I" if i == speaker else f"{who(i)} and {who(j)}"
        return f"{pair} are {'the same kind' if op == 'same' else 'of different kinds'}"
    if op == "count":
        k, knight = statement[1], statement[2]
        if k == 0:
            return f"none of the {len(names)} of us is a {_KIND[knight]}"
        return f"exactly {k} of the {len(names)} of us {'are' if k != 1 else 'is a'} {_KIND[knight]}{'s' if k != 1 else ''}"
    raise ValueError(op)


def _random_statement(rng: random.Random, n: int, speaker: int, difficulty: int) -> list:
    others = [i for i in range(n) if i != speaker]

    def atom() -> list:
        return ["is", rng.choice(others), rng.random() < 0.5]

    kinds = ["is", "same", "diff"] + (["and", "or"] if difficulty >= 2 else []) + \
        (["imp", "count"] if difficulty >= 3 else []) + (["iff", "not"] if difficulty >= 4 else [])
    kind = rng.choice(kinds)
    if kind == "is":
        return atom()
    if kind in ("same", "diff"):
        return [kind] + sorted(rng.sample(range(n), 2))
    if kind == "count":
        return ["count", rng.randint(0, n), rng.random() < 0.5]
    if kind == "not":
        return ["not", ["and", atom(), atom()] if difficulty >= 5 else atom()]
    a, b = atom(), atom()
    if a[1] == b[1]:
        return a
    return [kind, a, b]


def _make(rng: random.Random, difficulty: int, split: str, pool: tuple[str, ...]) -> dict[str, Any] | None:
    n = difficulty + 1
    names = rng.sample(pool, n)
    world = tuple(rng.random() < 0.5 for _ in range(n))
    statements: list = []
    speakers = list(range(n)) + [rng.randrange(n) for _ in range(2)]
    for speaker in speakers:
        for _ in range(50):  # a statement whose truth matches the speaker's kind
            s = _random_statement(rng, n, speaker, difficulty)
            if evaluate(s, world) == world[speaker]:
                statements.append([speaker, s])
                break
        else:
            return None
        if len(statements) >= n:
            found = models(n, statements)
            if found == [world]:
                break
    else:
        return None
    solution = {names[i]: _KIND[world[i]] for i in range(n)}
    lines = [f'{names[sp]} says: "{_capitalize(render(s, names, sp))}."' for sp, s in statements]
    listed = ", ".join(names[:-1]) + f" and {names[-1]}"
    prompt = (f"On an island, every inhabitant is either a knight, who always tells the truth, or a knave, who "
              f"always lies. You meet {n} inhabitants: {listed}.\n" + "\n".join(lines) + "\n"
              "Who is a knight and who is a knave? Name every inhabitant, like \"X is a knight, Y is a knave\", "
              "and put the final answer inside <answer></answer> tags.")
    gold = "<answer>" + ", ".join(f"{name} is a {kind}" for name, kind in solution.items()) + "</answer>"
    reference = {"family": FAMILY, "names": names, "statements": statements, "solution": solution,
                 "split": split, "difficulty": difficulty}
    return {"prompt": prompt, "reference": reference, "gold": gold}


def _capitalize(s: str) -> str:
    return s[:1].upper() + s[1:]


def generate(n: int, seed: int = 0, split: Split = "train", difficulty: int = 2) -> list[dict[str, Any]]:
    """`n` distinct puzzles with unique solutions: [{"prompt", "reference", "gold"}, ...], deterministic."""
    check_generate_args(n, split, difficulty, DIFFICULTIES)
    rng = make_rng(FAMILY, seed, split, difficulty)
    pool = TRAIN_NAMES if split == "train" else TEST_NAMES
    return generate_unique(n, rng, lambda r: _make(r, difficulty, split, pool),
                           lambda x: tuple(sorted(x["reference"]["solution"].items())), "knights_knaves.generate")


# ---------------------------------------------------------------------- answers
def _name_pattern(names: list[str]) -> str:
    parts = []
    for name in sorted(names, key=len, reverse=True):
        escaped = re.escape(name)
        parts.append(f"(?-i:{escaped})" if len(name) == 1 else escaped)
    return "(?:" + "|".join(parts) + ")"


def read_assignments(text: str, names: list[str]) -> dict[str, set[bool]]:
    """name -> the kinds the text gives it (True: knight)."""
    lookup = {name.lower(): name for name in names}
    N = _name_pattern(names)
    found: dict[str, set[bool]] = {}

    def put(name: str, knight: bool) -> None:
        key = name if name in names else lookup[name.lower()]
        found.setdefault(key, set()).add(knight)

    def names_in(group: str) -> list[str]:
        return re.findall(rf"(?<![\w]){N}(?![\w])", group, re.I)

    single = re.compile(rf"(?<![\w])({N})\s*(?:(?:is|was|must be|has to be|is definitely|would be)\s+(not\s+)?"
                        rf"|(isn't|is\s+not)\s+|[:=\-–—]\s*|\(\s*)(?:an?\s+)?(knight|knave)s?\b", re.I)
    for m in single.finditer(text):
        negated = bool(m.group(2) or m.group(3))
        put(m.group(1), (m.group(4).lower() == "knight") != negated)
    several = rf"{N}(?:\s*,\s*(?:and\s+)?{N}|\s*,?\s+(?:and|&)\s+{N})+"
    group = re.compile(rf"(?<![\w])({several})(?:\s+(?:are|were)\s+(not\s+)?|\s*[:=]\s*)(?:both\s+|all\s+)?"
                       rf"(knights|knaves)\b", re.I)
    for m in group.finditer(text):
        for name in names_in(m.group(1)):
            put(name, (m.group(3).lower() == "knights") != bool(m.group(2)))
    listed = re.compile(rf"(?:^|\bthe\s+|[;,.]\s*)(knights?|knaves?)\s*(?::|=|\bare\b|\bis\b)\s*"
                        rf"({N}(?:\s*(?:,|&|\band\b)\s*{N})*)", re.I | re.M)
    for m in listed.finditer(text):
        for name in names_in(m.group(2)):
            put(name, m.group(1).lower().startswith("knight"))
    return found


def _strangers(text: str, names: list[str]) -> list[str]:
    known = {n.lower() for n in names}
    pattern = re.compile(r"(?<![\w])([A-Z][a-z]+)\s*(?:(?:is|was)\s+(?:not\s+)?(?:an?\s+)?|[:=]\s*(?:an?\s+)?)(?:knight|knave)s?\b")
    return sorted({w for w in pattern.findall(text) if w.lower() not in known and w.lower() not in _NOT_NAMES})


def _text_scope(text: str, names: list[str]) -> str | None:
    markers = list(_MARKER.finditer(text))
    if markers:
        tail = text[markers[-1].end():]
        if read_assignments(tail, names):
            return tail
    for paragraph in reversed(re.split(r"\n\s*\n", text)):
        if read_assignments(paragraph, names):
            return paragraph
    return None


# ---------------------------------------------------------------------- verifier
class KnightsKnavesVerifier(PuzzleVerifier):
    """Knights-and-knaves puzzles (module docstring): 1.0 when every inhabitant is assigned correctly."""

    name = "knights_knaves"
    description = "Knights and knaves: every inhabitant named knight or knave, matching the unique solution"
    family = FAMILY
    default_difficulty = 2
    generate = staticmethod(generate)

    def parse_reference(self, reference: Any) -> tuple[list[str], dict[str, bool]]:
        require(isinstance(reference, dict), "knights_knaves reference must be a dict with 'names' and 'solution'")
        names, solution = reference.get("names"), reference.get("solution")
        require(isinstance(names, list) and bool(names) and all(isinstance(x, str) and x.strip() for x in names)
                and len({x.lower() for x in names}) == len(names),
                f"knights_knaves reference 'names' must be distinct non-empty strings, got {names!r}")
        require(isinstance(solution, dict) and set(solution) == set(names)
                and all(v in ("knight", "knave") for v in solution.values()),
                "knights_knaves reference 'solution' must map every name to 'knight' or 'knave'")
        truth = {name: solution[name] == "knight" for name in names}
        statements = reference.get("statements")
        if statements is not None:
            require(len(names) <= 12, "knights_knaves reference: too many inhabitants to check (max 12)")
            world = tuple(truth[name] for name in names)
            found = models(len(names), statements)
            require(found == [world], f"knights_knaves reference: the statements have {len(found)} solution(s) "
                                      "and the given solution must be the only one")
        return names, truth

    def check_scope(self, scope: str, rule: str, ref: tuple[list[str], dict[str, bool]]) -> Verdict:
        names, truth = ref
        text = strip_markup(scope)
        if rule == "text":
            found_scope = _text_scope(text, names)
            if found_scope is None:
                return Verdict(0.0, "no answer found", {"rule": rule})
            text = found_scope
        details: dict[str, Any] = {"rule": rule, "answer": text.strip()[:300]}
        if _HEDGE.search(text):
            return Verdict(0.0, "hedged answer", details)
        strangers = _strangers(text, names)
        if strangers:
            return Verdict(0.0, f"assigns {', '.join(strangers)}, who is not in the puzzle", details)
        found = read_assignments(text, names)
        details["assigned"] = {name: sorted(_KIND[k] for k in kinds) for name, kinds in found.items()}
        if not found:
            return Verdict(0.0, "no answer found", details)
        both = [name for name in names if len(found.get(name, ())) > 1]
        if both:
            return Verdict(0.0, f"contradictory: {', '.join(both)} called both knight and knave", details)
        missing = [name for name in names if name not in found]
        if missing:
            return Verdict(0.0, f"unassigned: {', '.join(missing)}", details)
        wrong = [name for name in names if next(iter(found[name])) != truth[name]]
        if wrong:
            return Verdict(0.0, f"wrong: {', '.join(wrong)}", details)
        return Verdict(1.0, "correct", details)

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        names, truth = self.parse_reference(problem.reference)

        def says(world: dict[str, bool], who: list[str]) -> str:
            return ", ".join(f"{name} is a {_KIND[world[name]]}" for name in who)

        flipped = {name: not k for name, k in truth.items()}
        one_flipped = dict(truth, **{names[0]: not truth[names[0]]})
        stranger = next(s for s in ("Zed", "Quill", "Xavi") if s.lower() not in {n.lower() for n in names})
        return [
            ("both options for everyone", "<answer>" + ", ".join(f"{n} is a knight or a knave" for n in names) + "</answer>", 0.0),
            ("both full assignments", f"<answer>{says(truth, names)}; or else {says(flipped, names)}</answer>", 0.0),
            ("one inhabitant unassigned", f"<answer>{says(truth, names[:-1])}</answer>", 0.0),
            ("contradiction", f"<answer>{says(truth, names)}, {names[0]} is a {_KIND[not truth[names[0]]]}</answer>", 0.0),
            ("everyone flipped", f"<answer>{says(flipped, names)}</answer>", 0.0),
            ("one flipped", f"<answer>{says(one_flipped, names)}</answer>", 0.0),
            ("a stranger added", f"<answer>{says(truth, names)}, {stranger} is a knight</answer>", 0.0),
            ("names without roles", "<answer>" + ", ".join(names) + "</answer>", 0.0),
            ("everyone is a knight", "<answer>Everyone is a knight.</answer>" if not all(truth.values())
             else "<answer>Everyone is a knave.</answer>", 0.0),
            ("hedged", f"<answer>{says(truth, names)}, but it could be the other way round</answer>", 0.0),
        ]
