"""Knights and knaves: knights always tell the truth, knaves always lie; who is which?

Reference: ``{"family": "knights_knaves", "names": [...], "solution": {name: "knight"|"knave"},
"statements": [[speaker_index, statement], ...]}`` (statements optional for checking; when
present the solution is verified to be their only model, else the reference raises).
Statements are JSON trees: ``["is", i, true]`` (i is a knight; false: a knave), ``["not", S]``,
``["and"|"or"|"imp"|"iff", S, T]``, ``["same"|"diff", i, j]``, ``["count", k, true]`` (exactly k
of the inhabitants are knights; false: knaves).

Role words. Puzzles often name the two roles otherwise (saints/sinners, heroes/villains,
truth-tellers/liars, angels/devils, altruists/egoists, sages/fools, pioneers/laggards, or even
knaves who tell the truth and knights who lie). The puzzle's pair is read, in this order, from
``reference["roles"]`` (``[truthful, liar]``, or ``{"knight": truthful, "knave": liar}``), from
``reference["knight_knave"]`` (the K&K dataset's ``{"knight": ..., "knave": ...}``), from the
solution's values when they are words of a known pair (``{"Alice": "saint", ...}``), and from
the puzzle text in ``reference["prompt"]`` / ``"quiz"`` / ``"question"`` / ``"problem"`` ("a saint,
who always tells the truth", "Heroes always tell the truth"); otherwise it is knight/knave. The
solution may be written in the puzzle's words, as knight/knave, or as booleans (a dict, or a
list aligned with ``names``; True: tells the truth).

An answer may name each inhabitant's role with the puzzle's words, with knight/knave, or with
truth-teller/liar (singular or plural, any capitalisation, "truth teller"/"truthteller"), and
with "tells the truth" / "lies". The puzzle's own words win: when they collide with the
standard words in the opposite sense (knaves who tell the truth), the standard pair is not
read at all, so "knight" means what the puzzle says. An answer that assigns roles with the
words of another pair ("angel" in a saints-and-sinners puzzle) scores 0 ("uses role words
... not in this puzzle"); one that gives somebody two opposite roles, in whatever words, is
"contradictory".

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
the same inhabitants and solution, so one puzzle's gold never solves another. ``roles=(truthful,
liar)`` words the puzzle, its gold and its solution with another pair (the reference then
carries ``"roles"``); the default output is knights and knaves.
"""
from __future__ import annotations

import itertools
import random
import re
from functools import lru_cache
from typing import Any

from posttrain.verifiers.base import AuditProblem, Verdict
from posttrain.verifiers.puzzles.common import (PuzzleVerifier, Split, check_generate_args, generate_unique, make_rng,
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
_HEDGE_WORDS = re.compile(r"\beither\b|\bcould be\b|\bmight be\b|\bmay be\b|\bunknown\b|\bundetermined\b|\bunclear\b"
                          r"|\bcannot be determined\b|\bcan't be determined\b|\bnot determined\b", re.I)
_MARKER = re.compile(r"\b(?:final answer|answer|conclusion|solution)\b", re.I)
# role pairs seen in the wild (truthful first); the first is the default
# (words are normalised: lower case, one space for "-" / "_" / spaces, so "truth-teller" is "truth teller")
KNOWN_PAIRS = (("knight", "knave"), ("saint", "sinner"), ("hero", "villain"), ("angel", "devil"),
               ("altruist", "egoist"), ("sage", "fool"), ("pioneer", "laggard"), ("truth teller", "liar"),
               ("truthteller", "liar"))
_STANDARD = (("knight", True), ("knave", False))
_DESCRIPTIVE = (("truth teller", True), ("truthteller", True), ("liar", False))
_PROMPT_KEYS = ("prompt", "quiz", "question", "problem")


def _norm_role(word: str) -> str:
    return re.sub(r"[\s_-]+", " ", word.strip().lower())


def _singular(word: str) -> str:
    w = _norm_role(word)
    if w.endswith("ies") and len(w) > 4:
        return w[:-3] + "y"
    if w.endswith(("ses", "xes", "ches", "shes", "oes")):
        return w[:-2]
    if w.endswith("s") and not w.endswith("ss"):
        return w[:-1]
    return w


def _plural(word: str) -> str:
    w = _norm_role(word)
    if w.endswith("y") and len(w) > 2 and w[-2] not in "aeiou":
        return w[:-1] + "ies"
    if w.endswith(("s", "x", "ch", "sh", "o")):
        return w + "es"
    return w + "s"


def _article(word: str) -> str:
    return ("an " if word[:1].lower() in "aeiou" else "a ") + word


def _forms(word: str) -> set[str]:
    """A role word as written, its singular and its plurals ("hero": hero, heroes, heros)."""
    w = _norm_role(word)
    return {w, _singular(w), _plural(w), w + "s", _plural(_singular(w))}


@lru_cache(maxsize=1024)
def _role_pattern(words: tuple[str, ...]) -> str:
    """Regex alternation for role words, singular or plural; spaces and hyphens inside a word interchange."""
    stems = set()
    for w in words:
        w = _singular(w)
        if w.endswith("y") and len(w) > 2 and w[-2] not in "aeiou":
            stems.add(re.escape(w[:-1]).replace(r"\ ", r"[\s-]?") + "(?:y|ies)")
        else:
            stems.add(re.escape(w).replace(r"\ ", r"[\s-]?") + "(?:es|s)?")
    return "(?:" + "|".join(sorted(stems, key=len, reverse=True)) + ")"


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


def render(statement: list, names: list[str], speaker: int, kinds: dict[bool, str] = _KIND) -> str:
    def who(i: int) -> str:
        return "I" if i == speaker else names[i]

    op = statement[0]
    if op == "is":
        i, knight = statement[1], statement[2]
        return f"{'I am' if i == speaker else names[i] + ' is'} {_article(kinds[knight])}"
    if op == "not":
        inner = statement[1]
        both = "both " if inner[0] == "and" else ""  # "not (A and B)", never read as "(not A) and B"
        return f"it is not true that {both}{render(inner, names, speaker, kinds)}"
    if op in ("and", "or", "imp", "iff"):
        a, b = render(statement[1], names, speaker, kinds), render(statement[2], names, speaker, kinds)
        return {"and": f"{a} and {b}", "or": f"{a} or {b}", "imp": f"if {a}, then {b}",
                "iff": f"{a} if and only if {b}"}[op]
    if op in ("same", "diff"):
        i, j = statement[1], statement[2]
        pair = f"{who(j)} and I" if i == speaker else f"{who(i)} and {who(j)}"
        return f"{pair} are {'the same kind' if op == 'same' else 'of different kinds'}"
    if op == "count":
        k, knight = statement[1], statement[2]
        if k == 0:
            return f"none of the {len(names)} of us is {_article(kinds[knight])}"
        if k == 1:
            return f"exactly 1 of the {len(names)} of us is {_article(kinds[knight])}"
        return f"exactly {k} of the {len(names)} of us are {_plural(kinds[knight])}"
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


def _make(rng: random.Random, difficulty: int, split: str, pool: tuple[str, ...],
          roles: tuple[str, str] | None = None) -> dict[str, Any] | None:
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
    return _build(names, world, statements, split, difficulty, roles)


def _build(names: list[str], world: tuple[bool, ...], statements: list, split: str, difficulty: int,
           roles: tuple[str, str] | None = None) -> dict[str, Any]:
    """Prompt, reference and gold of a puzzle, worded with `roles` (truthful, liar) or knights and knaves."""
    kinds = _KIND if roles is None else {True: roles[0], False: roles[1]}
    n = len(names)
    solution = {names[i]: kinds[world[i]] for i in range(n)}
    lines = [f'{names[sp]} says: "{_capitalize(render(s, names, sp, kinds))}."' for sp, s in statements]
    listed = ", ".join(names[:-1]) + f" and {names[-1]}"
    t, f = _article(kinds[True]), _article(kinds[False])
    prompt = (f"On an island, every inhabitant is either {t}, who always tells the truth, or {f}, who "
              f"always lies. You meet {n} inhabitants: {listed}.\n" + "\n".join(lines) + "\n"
              f"Who is {t} and who is {f}? Name every inhabitant, like \"X is {t}, Y is {f}\", "
              "and put the final answer inside <answer></answer> tags.")
    gold = "<answer>" + ", ".join(f"{name} is {_article(kind)}" for name, kind in solution.items()) + "</answer>"
    reference = {"family": FAMILY, "names": names, "statements": statements, "solution": solution,
                 "split": split, "difficulty": difficulty}
    if roles is not None:
        reference["roles"] = [kinds[True], kinds[False]]
    return {"prompt": prompt, "reference": reference, "gold": gold}


def retheme(item: dict[str, Any], roles: tuple[str, str]) -> dict[str, Any]:
    """The same puzzle worded with another role pair (truthful, liar)."""
    ref = item["reference"]
    names = ref["names"]
    truth = _solution_truth(ref, names, _reference_roles(ref))
    world = tuple(truth[name] for name in names)
    return _build(names, world, ref["statements"], ref.get("split", "train"), ref.get("difficulty", 2), roles)


def _capitalize(s: str) -> str:
    return s[:1].upper() + s[1:]


def generate(n: int, seed: int = 0, split: Split = "train", difficulty: int = 2,
             roles: tuple[str, str] | None = None) -> list[dict[str, Any]]:
    """`n` distinct puzzles with unique solutions: [{"prompt", "reference", "gold"}, ...], deterministic.

    `roles`: (truthful, liar) words to use instead of knight/knave (same puzzles otherwise).
    """
    check_generate_args(n, split, difficulty, DIFFICULTIES)
    if roles is not None:
        if (not isinstance(roles, (tuple, list)) or len(roles) != 2 or not all(isinstance(w, str) and w.strip() for w in roles)
                or _norm_role(roles[0]) == _norm_role(roles[1])):
            raise ValueError(f"generate: roles must be two different words (truthful, liar), got {roles!r}")
        roles = (roles[0].strip(), roles[1].strip())
    rng = make_rng(FAMILY, seed, split, difficulty)
    pool = TRAIN_NAMES if split == "train" else TEST_NAMES
    return generate_unique(n, rng, lambda r: _make(r, difficulty, split, pool, roles),
                           lambda x: tuple(sorted(x["reference"]["solution"].items())), "knights_knaves.generate")


# ---------------------------------------------------------------------- role words
def _reference_roles(reference: dict) -> tuple[str, str] | None:
    """The puzzle's (truthful, liar) words when the reference names a pair other than the default."""
    roles = reference.get("roles")
    if roles is None and isinstance(reference.get("knight_knave"), dict):
        roles = reference["knight_knave"]
    if roles is not None:
        if isinstance(roles, dict):
            t = next((roles[k] for k in ("knight", "truthful", "truth", "true") if k in roles), None)
            f = next((roles[k] for k in ("knave", "liar", "lie", "false") if k in roles), None)
            roles = (t, f)
        require(isinstance(roles, (list, tuple)) and len(roles) == 2 and all(isinstance(w, str) and w.strip() for w in roles)
                and _singular(roles[0]) != _singular(roles[1]),
                f"knights_knaves reference 'roles' must be two different words (truthful, liar), got {roles!r}")
        return _norm_role(roles[0]), _norm_role(roles[1])
    solution = reference.get("solution")
    if isinstance(solution, dict):
        values = {_singular(v) for v in solution.values() if isinstance(v, str)}
        for t, f in KNOWN_PAIRS:
            if values and values <= {t, f} and not values <= {"knight", "knave"}:
                return t, f
    for key in _PROMPT_KEYS:
        text = reference.get(key)
        if isinstance(text, str):
            found = _roles_from_text(text)
            if found is not None:
                return found
    return None


_ROLE_STOP = {"who", "that", "always", "and", "they", "people", "inhabitants", "ones", "others", "members", "some",
              "all", "one", "each", "every", "the", "a", "an", "never", "to"}
_TRUTH_RE = re.compile(r"(?i)\b([A-Za-z][A-Za-z-]*)(?:\s+(tellers?))?,?\s+(?:who\s+|that\s+)?(?:always\s+)?"
                       r"(?:tells?|speaks?)\s+the\s+truth")
_LIE_RE = re.compile(r"(?i)\b([A-Za-z][A-Za-z-]*)(?:\s+(tellers?))?,?\s+(?:who\s+|that\s+)?(?:always\s+)?lies?\b")


def _roles_from_text(text: str) -> tuple[str, str] | None:
    """("saint", "sinner") from "...saints and sinners. Saints always tell the truth, and sinners always lie"."""
    def first(pattern: re.Pattern) -> str | None:
        for m in pattern.finditer(text[:20000]):
            if m.group(1).lower() in _ROLE_STOP:
                continue
            return _singular(m.group(1) + (" " + m.group(2) if m.group(2) else ""))
        return None

    t, f = first(_TRUTH_RE), first(_LIE_RE)
    if t and f and t != f:
        return t, f
    return None


@lru_cache(maxsize=256)
def _vocabulary(roles: tuple[str, str] | None) -> tuple[tuple[str, bool], ...]:
    """Accepted role words -> truthful?: the puzzle's pair, plus the standard and descriptive words
    unless one of them means the opposite in this puzzle."""
    own = (("knight", True), ("knave", False)) if roles is None else ((roles[0], True), (roles[1], False))
    vocab = {}
    for w, k in own:
        for form in _forms(w):
            vocab.setdefault(form, k)
    for extra in (_STANDARD, _DESCRIPTIVE):
        if all(vocab.get(w, k) == k for w, k in extra):
            for w, k in extra:
                vocab.setdefault(w, k)
    return tuple(sorted(vocab.items()))


@lru_cache(maxsize=256)
def _foreign_words(vocab: tuple[tuple[str, bool], ...]) -> tuple[tuple[str, bool], ...]:
    """Role words of other known pairs (read only to reject an answer that uses them)."""
    accepted = {w for w, _ in vocab}
    out = {}
    for t, f in KNOWN_PAIRS:
        for w, k in ((t, True), (f, False)):
            if not _forms(w) & accepted:
                out[w] = k
    return tuple(sorted(out.items()))


def _solution_truth(reference: dict, names: list[str], roles: tuple[str, str] | None) -> dict[str, bool]:
    solution = reference.get("solution")
    if isinstance(solution, list):
        require(len(solution) == len(names) and all(isinstance(v, bool) for v in solution),
                "knights_knaves reference 'solution' as a list must hold one bool per name")
        return dict(zip(names, solution))
    require(isinstance(solution, dict) and set(solution) == set(names),
            "knights_knaves reference 'solution' must map every name to its role")
    lookup = dict(_vocabulary(roles))
    truth = {}
    for name in names:
        v = solution[name]
        if isinstance(v, bool):
            truth[name] = v
            continue
        key = _singular(v) if isinstance(v, str) else None
        if isinstance(v, str) and _norm_role(v) in lookup:
            key = _norm_role(v)
        require(key in lookup, f"knights_knaves reference 'solution' must map every name to a role word of the "
                               f"puzzle ({', '.join(w for w, _ in lookup.items())}) or a bool; got {v!r} for {name!r}")
        truth[name] = lookup[key]
    return truth


# ---------------------------------------------------------------------- answers
def _name_pattern(names: list[str]) -> str:
    parts = []
    for name in sorted(names, key=len, reverse=True):
        escaped = re.escape(name)
        parts.append(f"(?-i:{escaped})" if len(name) == 1 else escaped)
    return "(?:" + "|".join(parts) + ")"


class _Patterns:
    """The compiled answer patterns for one puzzle's names and accepted role words."""

    def __init__(self, names: tuple[str, ...], vocab: tuple[tuple[str, bool], ...]):
        self.names = list(names)
        self.lookup = {}
        for w, k in vocab:
            for form in _forms(w):
                self.lookup.setdefault(form, k)
        N = _name_pattern(self.names)
        R = _role_pattern(tuple(sorted({_singular(w) for w, _ in vocab})))
        self.N = N
        self.names_re = re.compile(rf"(?<![\w]){N}(?![\w])", re.I)
        self.single = re.compile(
            rf"(?<![\w])({N})\s*(?:(?:is|was|must be|has to be|is definitely|would be)\s+(not\s+)?"
            rf"|(isn't|is\s+not)\s+|[:=\-–—]\s*|\(\s*)(?:an?\s+)?({R})(?![\w])", re.I)
        several = rf"{N}(?:\s*,\s*(?:and\s+)?{N}|\s*,?\s+(?:and|&)\s+{N})+"
        self.group = re.compile(rf"(?<![\w])({several})(?:\s+(?:are|were)\s+(not\s+)?|\s*[:=]\s*)(?:both\s+|all\s+)?"
                                rf"({R})(?![\w])", re.I)
        self.listed = re.compile(rf"(?:^|\bthe\s+|[;,.]\s*)({R})\s*(?::|=|\bare\b|\bis\b)\s*"
                                 rf"({N}(?:\s*(?:,|&|\band\b)\s*{N})*)", re.I | re.M)
        self.verbs = re.compile(
            rf"(?<![\w])({N})\s+(?:(always\s+tells\s+the\s+truth|tells\s+the\s+truth|is\s+truthful|is\s+honest"
            rf"|is\s+telling\s+the\s+truth|never\s+lies|does\s+not\s+lie|doesn't\s+lie)"
            rf"|(always\s+lies|lies|is\s+lying|never\s+tells\s+the\s+truth|does\s+not\s+tell\s+the\s+truth"
            rf"|doesn't\s+tell\s+the\s+truth))(?![\w])", re.I)
        self.conjoined = re.compile(rf"(?<![\w])({N})\s*(?:(?:is|was)\s+|[:=\-–—]\s*)(?:an?\s+)?{R}"
                                    rf"(?:\s+(?:and|but\s+also|as\s+well\s+as)\s+(?:also\s+)?|\s*\(\s*(?:i\.e\.,?\s*|that\s+is,?\s*)?)"
                                    rf"(?:an?\s+)?({R})(?![\w])", re.I)
        self.hedge = re.compile(rf"\b{R}\s*(?:or|/|and/or)\s*(?:an?\s+)?{R}(?![\w])", re.I)

    def kind(self, word: str) -> bool:
        w = _norm_role(word)
        for key in (w, _singular(w), w.replace("truthteller", "truth teller"), _singular(w.replace("truthteller", "truth teller"))):
            if key in self.lookup:
                return self.lookup[key]
        raise KeyError(word)

    def read(self, text: str) -> dict[str, set[bool]]:
        lookup = {name.lower(): name for name in self.names}
        found: dict[str, set[bool]] = {}

        def put(name: str, knight: bool) -> None:
            key = name if name in self.names else lookup[name.lower()]
            found.setdefault(key, set()).add(knight)

        for m in self.single.finditer(text):
            negated = bool(m.group(2) or m.group(3))
            put(m.group(1), self.kind(m.group(4)) != negated)
        for m in self.conjoined.finditer(text):  # "Alice is a saint and a knave": the second role too
            put(m.group(1), self.kind(m.group(2)))
        for m in self.group.finditer(text):
            for name in self.names_re.findall(m.group(1)):
                put(name, self.kind(m.group(3)) != bool(m.group(2)))
        for m in self.listed.finditer(text):
            for name in self.names_re.findall(m.group(2)):
                put(name, self.kind(m.group(1)))
        for m in self.verbs.finditer(text):
            put(m.group(1), bool(m.group(2)))
        return found


_PATTERN_CACHE: dict[tuple, _Patterns] = {}


def _patterns(names: list[str], vocab: tuple[tuple[str, bool], ...]) -> _Patterns:
    key = (tuple(names), vocab)
    pat = _PATTERN_CACHE.get(key)
    if pat is None:
        if len(_PATTERN_CACHE) > 512:
            _PATTERN_CACHE.clear()
        pat = _PATTERN_CACHE[key] = _Patterns(tuple(names), vocab)
    return pat


@lru_cache(maxsize=512)
def _foreign_res(names: tuple[str, ...], foreign: tuple[tuple[str, bool], ...]) -> tuple[re.Pattern, re.Pattern]:
    """Assignments in the words of another pair: "Alice is an angel", "Angels: Alice"."""
    N = _name_pattern(list(names))
    F = _role_pattern(tuple(sorted({_singular(w) for w, _ in foreign})))
    named = re.compile(rf"(?<![\w]){N}(?:\s*,\s*(?:and\s+)?{N}|\s*,?\s+(?:and|&)\s+{N})*\s*(?:(?:is|was|are|were)\s+(?:not\s+)?"
                       rf"(?:all\s+|both\s+)?(?:an?\s+)?|[:=(\-–—]\s*(?:an?\s+)?)({F})(?![\w])", re.I)
    listed = re.compile(rf"(?:^|\bthe\s+|[;,.]\s*)({F})\s*(?::|=|\bare\b|\bis\b)\s*{N}", re.I | re.M)
    return named, listed


def read_assignments(text: str, names: list[str], roles: tuple[str, str] | None = None) -> dict[str, set[bool]]:
    """name -> the kinds the text gives it (True: tells the truth), reading the accepted role words."""
    return _patterns(names, _vocabulary(roles)).read(text)


def _strangers(text: str, names: list[str], role_pattern: str) -> list[str]:
    known = {n.lower() for n in names}
    pattern = re.compile(r"(?<![\w])([A-Z][a-z]+)\s*(?:(?:is|was)\s+(?:not\s+)?(?:an?\s+)?|[:=]\s*(?:an?\s+)?)"
                         + role_pattern + r"(?![\w])", re.I)
    return sorted({w for w in pattern.findall(text) if w[:1].isupper() and w.lower() not in known
                   and w.lower() not in _NOT_NAMES})


def _text_scope(text: str, pat: _Patterns) -> str | None:
    markers = list(_MARKER.finditer(text))
    if markers:
        tail = text[markers[-1].end():]
        if pat.read(tail):
            return tail
    for paragraph in reversed(re.split(r"\n\s*\n", text)):
        if pat.read(paragraph):
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

    def parse_reference(self, reference: Any) -> tuple[list[str], dict[str, bool], tuple[str, str] | None]:
        require(isinstance(reference, dict), "knights_knaves reference must be a dict with 'names' and 'solution'")
        names = reference.get("names")
        require(isinstance(names, list) and bool(names) and all(isinstance(x, str) and x.strip() for x in names)
                and len({x.lower() for x in names}) == len(names),
                f"knights_knaves reference 'names' must be distinct non-empty strings, got {names!r}")
        roles = _reference_roles(reference)
        truth = _solution_truth(reference, names, roles)
        statements = reference.get("statements")
        if statements is not None and not isinstance(statements, str):  # the K&K dataset stores a repr string
            require(len(names) <= 12, "knights_knaves reference: too many inhabitants to check (max 12)")
            world = tuple(truth[name] for name in names)
            found = models(len(names), statements)
            require(found == [world], f"knights_knaves reference: the statements have {len(found)} solution(s) "
                                      "and the given solution must be the only one")
        return names, truth, roles

    def check_scope(self, scope: str, rule: str, ref: tuple[list[str], dict[str, bool], tuple[str, str] | None]) -> Verdict:
        names, truth, roles = ref
        vocab = _vocabulary(roles)
        pat = _patterns(names, vocab)
        words = _own_words(roles)
        text = strip_markup(scope)
        if rule == "text":
            found_scope = _text_scope(text, pat)
            if found_scope is None:
                return Verdict(0.0, "no answer found", {"rule": rule})
            text = found_scope
        details: dict[str, Any] = {"rule": rule, "answer": text.strip()[:300]}
        if roles is not None:
            details["roles"] = [roles[0], roles[1]]
        if pat.hedge.search(text) or _HEDGE_WORDS.search(text):
            return Verdict(0.0, "hedged answer", details)
        foreign = _foreign_words(vocab)
        all_roles = _role_pattern(tuple(sorted({_singular(w) for w, _ in vocab + foreign})))
        strangers = _strangers(text, names, all_roles)
        if strangers:
            return Verdict(0.0, f"assigns {', '.join(strangers)}, who is not in the puzzle", details)
        if foreign:
            used = [m.group(1) for rx in _foreign_res(tuple(names), foreign) for m in rx.finditer(text)]
            if used:
                odd = sorted({_singular(u) for u in used})
                return Verdict(0.0, f"uses role words not in this puzzle ({', '.join(odd)}; "
                                    f"the puzzle's are {words[True]}/{words[False]})", details)
        found = pat.read(text)
        details["assigned"] = {name: sorted(words[k] for k in kinds) for name, kinds in found.items()}
        if not found:
            return Verdict(0.0, "no answer found", details)
        both = [name for name in names if len(found.get(name, ())) > 1]
        if both:
            return Verdict(0.0, f"contradictory: {', '.join(both)} called both {words[True]} and {words[False]}", details)
        missing = [name for name in names if name not in found]
        if missing:
            return Verdict(0.0, f"unassigned: {', '.join(missing)}", details)
        wrong = [name for name in names if next(iter(found[name])) != truth[name]]
        if wrong:
            return Verdict(0.0, f"wrong: {', '.join(wrong)}", details)
        return Verdict(1.0, "correct", details)

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        """Generated puzzles; every other one re-worded with another role pair (AUDIT_ROLES, in turn)."""
        items = type(self).generate(n, seed, "train", self.default_difficulty)
        out = []
        for i, x in enumerate(items):
            roles = AUDIT_ROLES[(i // 2) % len(AUDIT_ROLES)] if i % 2 else None
            if roles is not None:
                x = retheme(x, roles)
            out.append(AuditProblem(prompt=x["prompt"], reference=x["reference"], gold=x["gold"]))
        return out

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        names, truth, roles = self.parse_reference(problem.reference)
        vocab = _vocabulary(roles)
        own = _own_words(roles)

        def says(world: dict[str, bool], who: list[str], kinds: dict[bool, str] = own) -> str:
            return ", ".join(f"{name} is {_article(kinds[world[name]])}" for name in who)

        flipped = {name: not k for name, k in truth.items()}
        one_flipped = dict(truth, **{names[0]: not truth[names[0]]})
        stranger = next(s for s in ("Zed", "Quill", "Xavi") if s.lower() not in {n.lower() for n in names})
        t, f = own[True], own[False]
        cases = [
            ("both options for everyone", "<answer>" + ", ".join(f"{n} is {_article(t)} or {_article(f)}" for n in names) + "</answer>", 0.0),
            ("both full assignments", f"<answer>{says(truth, names)}; or else {says(flipped, names)}</answer>", 0.0),
            ("one inhabitant unassigned", f"<answer>{says(truth, names[:-1])}</answer>", 0.0),
            ("contradiction", f"<answer>{says(truth, names)}, {names[0]} is {_article(own[not truth[names[0]]])}</answer>", 0.0),
            ("everyone flipped", f"<answer>{says(flipped, names)}</answer>", 0.0),
            ("one flipped", f"<answer>{says(one_flipped, names)}</answer>", 0.0),
            ("a stranger added", f"<answer>{says(truth, names)}, {stranger} is {_article(t)}</answer>", 0.0),
            ("names without roles", "<answer>" + ", ".join(names) + "</answer>", 0.0),
            ("everyone is truthful", f"<answer>Everyone is {_article(t)}.</answer>" if not all(truth.values())
             else f"<answer>Everyone is {_article(f)}.</answer>", 0.0),
            ("hedged", f"<answer>{says(truth, names)}, but it could be the other way round</answer>", 0.0),
        ]
        # role words: plurals and capitals, the other accepted words, and pairs this puzzle does not use
        tellers = [n for n in names if truth[n]]
        liars = [n for n in names if not truth[n]]
        listing = "; ".join(part for part in (
            (f"{_plural(t).capitalize()}: {', '.join(tellers)}" if tellers else ""),
            (f"{_plural(f).capitalize()}: {', '.join(liars)}" if liars else "")) if part)
        cases.append(("plural capitalised role words", f"<answer>{listing}</answer>", 1.0))
        cases.append(("truth-teller / liar words", f"<answer>{says(truth, names, {True: 'truth-teller', False: 'liar'})}</answer>",
                      1.0 if dict(vocab).get("liar") is False else 0.0))
        standard_ok = dict(vocab).get("knight") is True and dict(vocab).get("knave") is False
        if roles is not None and standard_ok:
            cases.append(("knight / knave words", f"<answer>{says(truth, names, _KIND)}</answer>", 1.0))
        if not standard_ok:  # knaves tell the truth here: the standard reading of the words is wrong
            cases.append(("standard reading of swapped words", f"<answer>{says(truth, names, _KIND)}</answer>", 0.0))
        other = next((p for p in KNOWN_PAIRS if p[0] not in dict(vocab) and p[1] not in dict(vocab)), None)
        if other is not None:
            cases.append(("another puzzle's role words", f"<answer>{says(truth, names, {True: other[0], False: other[1]})}</answer>", 0.0))
        cases.append(("mixed words, one wrong", f"<answer>{says(truth, names[:-1])}, {names[-1]} is "
                      f"{_article(('truth-teller' if not truth[names[-1]] else 'liar') if dict(vocab).get('liar') is False else own[not truth[names[-1]]])}</answer>", 0.0))
        return cases


def _own_words(roles: tuple[str, str] | None) -> dict[bool, str]:
    return dict(_KIND) if roles is None else {True: roles[0], False: roles[1]}


# audit puzzles are re-worded with these pairs in turn (the last one: knaves tell the truth)
AUDIT_ROLES = (("saint", "sinner"), ("hero", "villain"), ("truth-teller", "liar"), ("angel", "devil"),
               ("altruist", "egoist"), ("knave", "knight"))
