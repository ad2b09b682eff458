"""Worked example for "Writing a verifier" (verifiers/README.md): a multiple-choice verifier.

    python -m posttrain.verifiers.cli audit verifiers/examples/multiple_choice.py:MultipleChoiceVerifier
    python -m posttrain.verifiers.cli score verifiers/examples/multiple_choice.py:MultipleChoiceVerifier rows.jsonl

Reference: one letter "A".."E". The model's choice is the option letter ("C" or "(C)") in the
last sentence that names one; a sentence naming several different letters scores 0.
"""
from __future__ import annotations

import random
import re

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier

LETTER = re.compile(r"(?<![A-Za-z0-9])\(?([A-E])\)?(?![A-Za-z0-9])")
SENTENCE_END = re.compile(r"[.!?\n]+")


class MultipleChoiceVerifier(Verifier):
    """The option letter (A-E) of the last sentence that names one, vs the reference letter."""

    name = "multiple_choice"
    description = "multiple choice: the letter A-E in the last sentence naming one vs the reference"
    timeout_s = 2.0
    in_process = True  # linear regex scans: cheap and bounded

    def check(self, completion: str, reference: str) -> Verdict:
        # A malformed reference is a bug in the problem set: raise, never score it.
        if not (isinstance(reference, str) and re.fullmatch(r"[A-E]", reference.strip())):
            raise ValueError(f"multiple_choice: reference must be one letter A-E, got {reference!r}")
        gold = reference.strip()
        statements = [s for s in SENTENCE_END.split(completion) if LETTER.search(s)]
        if not statements:
            return Verdict(0.0, "no answer found", {"gold": gold})
        letters = sorted(set(LETTER.findall(statements[-1])))
        details = {"extracted": ",".join(letters), "gold": gold}
        if len(letters) > 1:  # "(B) or (C)": a hedge never earns credit
            return Verdict(0.0, "multiple answers", details)
        if letters[0] == gold:
            return Verdict(1.0, "correct", details)
        return Verdict(0.0, "wrong answer", details)

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        rng = random.Random(seed)
        problems = []
        for _ in range(n):
            a, b = rng.randint(2, 40), rng.randint(2, 40)
            options = rng.sample([a + b + d for d in range(-5, 6) if d], 4) + [a + b]
            rng.shuffle(options)
            letter = "ABCDE"[options.index(a + b)]
            listing = " ".join(f"({'ABCDE'[k]}) {x}" for k, x in enumerate(options))
            problems.append(AuditProblem(prompt=f"What is {a} + {b}? {listing}", reference=letter,
                                         gold=f"{a} + {b} = {a + b}, which is option ({letter})."))
        return problems

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        wrong = "A" if problem.reference != "A" else "B"
        return [
            ("two letters", f"The answer is ({wrong}) or ({problem.reference}).", 0.0),
            ("correction", f"I first thought ({wrong}). Checking again, it is ({problem.reference}).", 1.0),
            ("no letter", "I am not sure which option is right.", 0.0),
        ]


def exact_letter(completion: str, reference: str) -> bool:
    """A one-off check as a plain function: the whole completion is the letter."""
    return completion.strip().strip("()") == reference.strip()
