"""reasoning-gym's scorers behind the verifier interface (`pip install "posttrain[gym]"`).

reasoning-gym (open-thought/reasoning-gym) ships 100+ seeded procedural datasets (arithmetic, logic puzzles,
ciphers, games, graphs, ...), each with its own `score_answer(answer, entry)`. This verifier scores a
completion with the scorer of the dataset its reference names, so posttrain's runner gives those scorers the
same worker pool, hard timeouts and audit as the built-in verifiers.

    get_verifier("gym").check("<answer>-27</answer>", {"dataset": "basic_arithmetic", "entry": entry})

Reference: `{"dataset": NAME, "entry": {"question": ..., "answer": ..., "metadata": {...}}}`, a reasoning-gym
entry as `posttrain.tasks.gym` writes it into a row's `answer` (JSON: tuples in the metadata come back as
lists, which the scorers accept). A reference without them is a bug in the problem set and raises.

Answer extraction: the text of the LAST `<answer>...</answer>` in the completion (the format reasoning-gym's
own prompts ask for), stripped; a completion without one scores 0 ("no <answer> tag"). With
`tag=""` the whole completion is the answer.

Scores: what the dataset's scorer returns, clamped to [0, 1]. Several give partial credit (countdown 0.01 for a
well-formed wrong expression; spell_backward about 0.1 to an unrelated word, which the audit flags as a false
positive); `partial=False` scores 1 for a full score and 0 otherwise. A scorer that raises on model text is
reasoning-gym's bug, not the model's: the runner reports it with the row (it is not hidden as a 0).

Threat model: the scorers are library code that parses model text (some with sympy); they run in the
verifier pool's worker processes under its hard per-check timeout, not in the code sandbox. None of the
datasets posttrain's task adapter exposes executes model output as code.

This module imports reasoning-gym only when a GymVerifier is made, so the registry lists `gym` without it.
"""
from __future__ import annotations

import re
from typing import Any

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier

INSTALL = 'pip install "posttrain[gym]"'
AUDIT_DATASETS = ("basic_arithmetic", "chain_sum", "leg_counting", "spell_backward", "word_sorting")


def require_reasoning_gym():
    """The reasoning_gym module; ImportError with the pip command when it is not installed."""
    try:
        import reasoning_gym
    except ImportError:
        raise ImportError(f"the gym verifier and gym: tasks need reasoning-gym; install it with {INSTALL}") from None
    return reasoning_gym


class GymVerifier(Verifier):
    name = "gym"
    description = "reasoning-gym's scorer of the reference's dataset, on the last <answer> tag (posttrain[gym])"
    timeout_s = 10.0

    def __init__(self, tag: str = "answer", partial: bool = True):
        require_reasoning_gym()
        if tag and not re.fullmatch(r"[A-Za-z_][\w-]*", tag):
            raise ValueError(f"gym verifier: tag must be an XML-like tag name or '', got {tag!r}")
        self.tag, self.partial = tag, bool(partial)
        self._scorers: dict[str, Any] = {}

    def warmup(self) -> None:
        require_reasoning_gym()

    def _scorer(self, dataset: str):
        if dataset not in self._scorers:
            rg = require_reasoning_gym()
            if dataset not in rg.factory.DATASETS:
                raise ValueError(f"gym reference names dataset {dataset!r}, which reasoning-gym does not have")
            self._scorers[dataset] = rg.get_score_answer_fn(dataset)
        return self._scorers[dataset]

    def extract(self, completion: str) -> str | None:
        if not self.tag:
            return completion.strip()
        found = re.findall(rf"<{self.tag}>(.*?)</{self.tag}>", completion, flags=re.DOTALL)
        return found[-1].strip() if found else None

    def check(self, completion: str, reference: Any) -> Verdict:
        if not (isinstance(reference, dict) and isinstance(reference.get("dataset"), str)
                and isinstance(reference.get("entry"), dict) and "answer" in reference["entry"]):
            raise ValueError("gym reference must be {'dataset': NAME, 'entry': {question, answer, metadata}}, "
                             f"got {str(reference)[:200]}")
        dataset, entry = reference["dataset"], reference["entry"]
        answer = self.extract(completion)
        if answer is None:
            return Verdict(0.0, f"no <{self.tag}> tag", {"dataset": dataset})
        score = float(self._scorer(dataset)(answer, entry))
        score = min(1.0, max(0.0, score))
        if not self.partial and score < 1.0:
            score = 0.0
        reason = "correct" if score >= 1.0 else "wrong answer" if score == 0.0 else "partial credit"
        return Verdict(score, reason, {"dataset": dataset, "answer": answer[:200], "expected": str(entry["answer"])[:200]})

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        gold = str(problem.reference["entry"]["answer"])
        return [("the answer outside the tag", f"The answer is {gold}.", 0.0),
                ("an empty tag", "<answer></answer>", 0.0),
                ("the answer in another tag", f"<final>{gold}</final>", 0.0)]

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        rg = require_reasoning_gym()
        out: list[AuditProblem] = []
        per = max(1, -(-n // len(AUDIT_DATASETS)))
        for name in AUDIT_DATASETS:
            for entry in rg.create_dataset(name, size=per, seed=seed):
                entry = {"question": entry["question"], "answer": entry["answer"], "metadata": entry["metadata"]}
                out.append(AuditProblem(entry["question"], {"dataset": name, "entry": entry},
                                        f"<answer>{entry['answer']}</answer>"))
        return out[:n]
