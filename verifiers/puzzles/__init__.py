"""Logic-puzzle families behind `posttrain.verifiers.logic`: a seeded generator and an exact checker each.

- `countdown`: reach a target with + - * / over given numbers (each used at most once).
- `knights`: knights-and-knaves puzzles with a unique solution.
- `sudoku`: 4x4 sudoku (2x2 boxes) with a unique solution.

Import the verifiers from `posttrain.verifiers.logic`; this package holds their implementation.
"""
