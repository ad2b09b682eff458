"""4x4 sudoku (2x2 boxes): fill the grid so every row, column and box holds 1-4 once.

Reference: ``{"family": "sudoku", "puzzle": "1..4..1.........", "solution": "1234..."}``: 16
characters row by row, "." (or "0") for an empty cell; ``solution`` is optional. The puzzle
must have exactly one solution (checked by a solver; otherwise the reference raises).

Answer: 4 lines of 4 digits, with or without spaces, commas, bars or a "Row 1:" label
(separator lines such as "---+---" are skipped), or one line of 16 digits ("1234341221434321",
"[[1,2,3,4],[3,4,1,2],...]"). Scope: the ``<answer>`` tag / ``\\boxed{}`` content must hold
exactly one grid; in free text the last grid wins. The check is exact: the digits are 1-4,
every given is kept, and every row, column and box is a permutation of 1-4 (with a unique
solution that is the same as matching it). Scores 0 with reasons: "no grid found",
"not a 4x4 grid", "incomplete grid", "digit out of range", "changes the given ...",
"row/column/box ... repeats ...".

Generator: a solution drawn uniformly from all 288 grids, then givens removed in random order
while the solution stays unique, down to 10/8/6/5 givens for difficulty 1/2/3/4. Split: the
288 solution grids are partitioned by a stable hash (crc32 % 4 == 0: 76 held out for "test"), so
train and test puzzles never share a solution, let alone a puzzle. A batch no larger than its
split's grid count (212 train, 76 test) uses each solution grid at most once.
"""
from __future__ import annotations

import functools
import random
import re
import zlib
from typing import Any

from posttrain.verifiers.base import AuditProblem, Verdict
from posttrain.verifiers.puzzles.common import (PuzzleVerifier, Split, check_generate_args, generate_unique, make_rng,
                                      require, strip_markup)

FAMILY = "sudoku"
DIFFICULTIES = range(1, 5)
GIVENS = {1: 10, 2: 8, 3: 6, 4: 5}
_UNITS = ([[(r, c) for c in range(4)] for r in range(4)]
          + [[(r, c) for r in range(4)] for c in range(4)]
          + [[(br + r, bc + c) for r in range(2) for c in range(2)] for br in (0, 2) for bc in (0, 2)])
_UNIT_NAMES = [f"row {i + 1}" for i in range(4)] + [f"column {i + 1}" for i in range(4)] + \
    [f"box {i + 1}" for i in range(4)]
_ROW_LINE = re.compile(r"^[\s\[\](){},;|+\-–:=]*(?:[0-9._][\s\[\](){},;|+\-–:=]*)+$")


# ---------------------------------------------------------------------- solving
def _peers_ok(grid: list[int], i: int, d: int) -> bool:
    r, c = divmod(i, 4)
    for k in range(4):
        if grid[r * 4 + k] == d or grid[k * 4 + c] == d:
            return False
    br, bc = r - r % 2, c - c % 2
    return all(grid[(br + a) * 4 + bc + b] != d for a in range(2) for b in range(2))


def solutions(puzzle: list[int], limit: int = 2) -> list[list[int]]:
    """Up to `limit` solutions of a puzzle (0 = empty cell), by backtracking."""
    grid = list(puzzle)
    out: list[list[int]] = []

    def solve(i: int) -> None:
        if len(out) >= limit:
            return
        while i < 16 and grid[i]:
            i += 1
        if i == 16:
            out.append(list(grid))
            return
        for d in range(1, 5):
            if _peers_ok(grid, i, d):
                grid[i] = d
                solve(i + 1)
                grid[i] = 0

    solve(0)
    return out


@functools.lru_cache(maxsize=1)
def all_grids() -> tuple[str, ...]:
    """All 288 valid 4x4 sudoku grids, as 16-digit strings, sorted."""
    return tuple(sorted("".join(map(str, g)) for g in solutions([0] * 16, limit=1000)))


def in_test_split(grid: str) -> bool:
    return zlib.crc32(grid.encode()) % 4 == 0


def first_problem(grid: list[int]) -> str | None:
    """The first broken rule of a filled grid, or None when it is a valid solution."""
    for cells, unit in zip(_UNITS, _UNIT_NAMES):
        seen: set[int] = set()
        for r, c in cells:
            d = grid[r * 4 + c]
            if d in seen:
                return f"{unit} repeats {d}"
            seen.add(d)
    return None


# ---------------------------------------------------------------------- answers
def _cells(line: str) -> str:
    line = re.sub(r"(?i)^\s*(?:row|r)\s*\d\s*[:.)=\-]\s*", "", line)
    if not _ROW_LINE.match(line):
        return ""
    return "".join(re.findall(r"[0-9._]", line))


def read_grid(text: str, last: bool) -> tuple[str | None, str]:
    """(16-char grid or None, reason). `last`: free text, take the last grid; else exactly one grid."""
    text = strip_markup(text).replace("\\\\", "\n").replace("&", " ")
    found: list[tuple[int, str]] = []  # (line index, 16 cells)
    rows: list[tuple[int, str]] = []
    bad = 0
    for i, line in enumerate(text.splitlines()):
        cells = _cells(line)
        if len(cells) == 16:
            found.append((i, cells))
        elif len(cells) == 4:
            rows.append((i, cells))
        elif cells:
            bad += 1
    # consecutive runs of row lines (separator / blank lines between rows are allowed)
    runs: list[list[tuple[int, str]]] = []
    for row in rows:
        if runs and len(runs[-1]) < 4 and row[0] - runs[-1][-1][0] <= 2:
            runs[-1].append(row)
        else:
            runs.append([row])
    found += [(run[-1][0], "".join(cells for _, cells in run)) for run in runs if len(run) == 4]
    if not last:
        if len(found) != 1 or sum(len(run) for run in runs) % 4 or bad:
            if not found and not rows and not bad:
                return None, "no grid found"
            return None, "not a 4x4 grid" if len(found) <= 1 else "several grids"
        return found[0][1], ""
    if not found:
        return None, "no grid found"
    return max(found)[1], ""


# ---------------------------------------------------------------------- generator
def _make(rng: random.Random, grids: list[str], givens: int, split: str, difficulty: int) -> dict[str, Any] | None:
    solution = rng.choice(grids)
    puzzle = [int(ch) for ch in solution]
    order = list(range(16))
    rng.shuffle(order)
    for i in order:
        if sum(1 for d in puzzle if d) == givens:
            break
        keep = puzzle[i]
        puzzle[i] = 0
        if len(solutions(puzzle)) != 1:
            puzzle[i] = keep
    if sum(1 for d in puzzle if d) != givens:
        return None
    text = "".join(str(d) if d else "." for d in puzzle)
    reference = {"family": FAMILY, "puzzle": text, "solution": solution, "split": split, "difficulty": difficulty}
    gold = "<answer>\n" + "\n".join(solution[r * 4:(r + 1) * 4] for r in range(4)) + "\n</answer>"
    return {"prompt": _prompt(text), "reference": reference, "gold": gold}


def _show(puzzle: str) -> str:
    lines = []
    for r in range(4):
        row = puzzle[r * 4:(r + 1) * 4]
        lines.append(f"{row[0]} {row[1]} | {row[2]} {row[3]}")
        if r == 1:
            lines.append("----+----")
    return "\n".join(lines)


def _prompt(puzzle: str) -> str:
    return ("Solve this 4x4 sudoku. Fill every empty cell (.) with a digit from 1 to 4 so that each row, each "
            "column and each 2x2 box contains 1, 2, 3 and 4 exactly once.\n\n" + _show(puzzle) + "\n\n"
            "Give the completed grid as 4 lines of 4 digits inside <answer></answer> tags.")


def generate(n: int, seed: int = 0, split: Split = "train", difficulty: int = 2) -> list[dict[str, Any]]:
    """`n` distinct puzzles with unique solutions: [{"prompt", "reference", "gold"}, ...], deterministic."""
    check_generate_args(n, split, difficulty, DIFFICULTIES)
    rng = make_rng(FAMILY, seed, split, difficulty)
    grids = [g for g in all_grids() if in_test_split(g) == (split == "test")]
    # While the split has enough grids, no two puzzles of a batch share a solution, so one
    # puzzle's gold never solves another; beyond that, puzzles are distinct but may share one.
    field = "solution" if n <= len(grids) else "puzzle"
    return generate_unique(n, rng, lambda r: _make(r, grids, GIVENS[difficulty], split, difficulty),
                           lambda x: x["reference"][field], "sudoku.generate")


# ---------------------------------------------------------------------- verifier
class SudokuVerifier(PuzzleVerifier):
    """4x4 sudoku (module docstring): 1.0 when the grid keeps the givens and breaks no rule."""

    name = "sudoku"
    description = "4x4 sudoku: a completed grid that keeps the givens and satisfies every row, column and box"
    family = FAMILY
    default_difficulty = 2
    generate = staticmethod(generate)

    def parse_reference(self, reference: Any) -> list[int]:
        require(isinstance(reference, dict) and isinstance(reference.get("puzzle"), str),
                "sudoku reference must be a dict with 'puzzle' (16 characters, '.' or '0' for empty cells)")
        text = reference["puzzle"].replace("0", ".")
        require(len(text) == 16 and all(ch in ".1234" for ch in text),
                f"sudoku reference 'puzzle' must be 16 characters of 1-4 and '.', got {reference['puzzle']!r}")
        puzzle = [0 if ch == "." else int(ch) for ch in text]
        found = solutions(puzzle)
        require(len(found) == 1, f"sudoku reference puzzle has {len(found)} solution(s) (need exactly 1)")
        solution = reference.get("solution")
        if solution is not None:
            require(solution == "".join(map(str, found[0])), "sudoku reference 'solution' is not the puzzle's solution")
        return puzzle

    def check_scope(self, scope: str, rule: str, puzzle: list[int]) -> Verdict:
        grid_text, why = read_grid(scope, last=(rule == "text"))
        details: dict[str, Any] = {"rule": rule}
        if grid_text is None:
            return Verdict(0.0, why, details)
        details["grid"] = grid_text
        if any(ch in "._0" for ch in grid_text):
            return Verdict(0.0, "incomplete grid", details)
        if any(ch not in "1234" for ch in grid_text):
            return Verdict(0.0, "digit out of range", details)
        grid = [int(ch) for ch in grid_text]
        for i, (given, d) in enumerate(zip(puzzle, grid)):
            if given and given != d:
                return Verdict(0.0, f"changes the given {given} at row {i // 4 + 1}, column {i % 4 + 1}", details)
        problem = first_problem(grid)
        if problem is not None:
            return Verdict(0.0, problem, details)
        return Verdict(1.0, "correct", details)

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        puzzle = self.parse_reference(problem.reference)
        solution = "".join(map(str, solutions(puzzle)[0]))

        def rows(cells: str, n: int = 4) -> str:
            return "\n".join(cells[r * 4:(r + 1) * 4] for r in range(n))

        def grid(cells: str) -> str:
            return "<answer>\n" + rows(cells) + "\n</answer>"

        relabelled = solution.translate(str.maketrans("1234", "2341"))
        ones = "".join(str(d) if d else "1" for d in puzzle)
        other = next(g for g in all_grids() if g != solution)
        return [
            ("puzzle echoed with blanks", grid("".join(str(d) if d else "." for d in puzzle)), 0.0),
            ("valid grid that changes the givens", grid(relabelled), 0.0),
            ("givens kept, blanks filled with 1", grid(ones), 0.0),
            ("three rows only", "<answer>\n" + rows(solution, 3) + "\n</answer>", 0.0),
            ("digit out of range", grid(solution[:-1] + "5"), 0.0),
            ("two grids in one answer", "<answer>\n" + rows(solution) + "\n\n" + rows(other) + "\n</answer>", 0.0),
            ("one cell changed", grid(solution[:5] + ("1" if solution[5] != "1" else "2") + solution[6:]), 0.0),
            ("rows of five digits", "<answer>\n" + "\n".join(solution[r * 4:(r + 1) * 4] + "1" for r in range(4)) + "\n</answer>", 0.0),
        ]
