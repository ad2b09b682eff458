"""Math answer verifier (registry name "math"): extract the final answer, normalise it, compare to the gold.

The reference is the gold answer: a string (`"3/4"`, `"\\frac{3}{4}"`, `"(1, 2]"`, `"x = 3"`,
`"\\{1, 2\\}"`, `"25\\%"`, `"\\text{Evelyn}"`) or a number. A reference we cannot parse is a
bug in the problem set and raises ValueError. The completion is scored 1.0 or 0.0 with a reason:
"correct", "wrong answer", "no answer found", "unparseable answer", "multiple answers",
"answer retracted", "unevaluated expression" (only with `require_simplified=True`), "comparison
budget exceeded". A matrix reference (`\\begin{pmatrix}...`) is supported; another LaTeX
environment (`\\begin{cases}`) raises "unsupported reference". `details` holds
{"rule", "extracted", "normalized", "gold"} (and "error" for an unparseable answer).

Extraction policy (applied in this order; the first rule that finds something decides):

0. Scope. If the completion holds a closed `<answer>...</answer>` pair, only the content of the
   *last* pair is looked at (text after it is ignored, except a retraction: see below).
   Otherwise, if it holds `</think>`, the text after the last `</think>` is looked at first
   (falling back to the whole text when it yields nothing): tentative answers inside a
   reasoning block do not count.
1. `\\boxed{...}` / `\\fbox{...}` (balanced braces, nested braces and `\\{ \\}` handled).
2. An answer phrase: "the answer is ...", "final answer: ...", "answer: ...", "answer = ...",
   "the answer would/should/will/must be ...", "the answer equals ..." (case-insensitive, markdown
   `**` tolerated); "the answer isn't / is not ..." is a negated value (see Negations). The value
   runs to the end of the sentence (a "." followed by a space or the end; not the "..." of a
   repeating decimal "0.333...") or of the line; an empty rest of line takes the next non-empty line.
3. `#### ...` (GSM8K style), to the end of the line.
4. Inside an `<answer>` scope only: the whole tag content.
5. The last number in the text: a bare number (sign, thousands separators - commas, or single
   spaces / no-break spaces between groups of exactly three digits, "12 500" - decimals, a/b, `1e3`,
   `2.9 \\times 10^{4}`, `2^{10}`, percent, a factorial `4!` written right after the digits), a bare
   LaTeX run (`\\frac{a}{b}`, `7\\sqrt{5}`, `3\\pi`), an inline/display math segment (`$...$`, `$$...$$`,
   `\\(...\\)`, `\\[...\\]`), or an algebraic expression in plain text ("factors as (a-2)^2": single
   letters, numbers, `+ - * / ^` and brackets, no words; the numbers inside it are not candidates of
   their own), whichever ends last (inside an `<answer>` scope, when the whole content does not
   parse). A number right after a negation ("not 8", "isn't 8", "rather than 8") or right before
   "is wrong" is not a candidate, nor is an exponent (`cm^2`). Number words are not read by this fallback: in running prose they
   are mostly quantifiers ("the two cases"), so only an explicit answer (rules 1-4) reads them.

Within a rule, the LAST occurrence counts, so "the answer is 5. Wait, actually the answer is 6"
gives 6. Exactly: occurrences of the winning rule are ordered by position and the last one is
taken, together with the occurrences just before it that are separated from it only by
connectives (whitespace, `,` `;` `/` `&`, "and", "or", "either", `\\text{ or }`, `\\quad`, math
delimiters): those form one statement that offers several values.

Retractions. After the chosen answer, a self-referential retraction ("no wait", "wait, no",
"that's wrong/incorrect/not right", "this is wrong", "I made a mistake", "I was wrong",
"scratch that", "let me correct", "correction:", "on second thought", "actually, no"), or a
negated restatement of that very answer ("it isn't 8", "that's not 8", "the answer is not 8",
"8 is wrong"), voids it: the answer is re-extracted from the text after the retraction with the
same rules, and when that text holds none the verdict is "answer retracted". Third-person
phrases ("option C is wrong", "option 8 is wrong") and negations of something else ("it is not
prime") are not retractions.

Negations. A value that starts by negating ("not 8; it's 9", "it isn't 8, but 9", "The answer
isn't 8. It's 9.") withdraws what it negates and offers what follows, in the same sentence or
the next one ("It's 9." / "but 9"); with nothing after it, it is "unparseable answer" unless an
earlier statement of the same rule stands ("The answer is 2. The answer is not 3." gives 2).
A parenthetical negation ("5 (not 6)") offers nothing and is dropped.

Factorials. Inside math (`\\boxed{}`, `$...$`, `\\(...\\)`, `\\[...\\]`, a reference) `!` is the
factorial: `\\boxed{4!}` is 24, never 4 (reading it as 4 was a reward hack), `(n)!`,
`\\left(3\\right)!` and `n!` too; `5!!` is the double factorial 15; three or more `!` in a row are
"unparseable answer". In prose (answer phrases, `####`, `<answer>` text, the last-number rule) a
run of one or two `!` is a factorial only when it follows a digit or a closing bracket directly
("The answer is 4!" is 24), and punctuation otherwise ("5 apples!", "4 !", "$5$!", "wow!!!", and
a currency amount "$18!"). A careful grader cannot tell "4!" from an exclamation, so the
mathematical reading wins; a model that means 4 writes 4. "!=" is "not equal".

Several candidate answers (reward-hack guard). A statement that offers several *different*
values when the gold is a single value scores 0 with reason "multiple answers": adjacent
boxes (`\\boxed{3} or \\boxed{4}`), lists (`the answer is 3, 4, 5 or 6`), `\\pm` (`\\pm 3` is
{3, -3}). When the gold itself has several elements (a set, a list of roots), such a statement
is read as a set and compared to the gold set. Only one statement ever counts, so spreading
guesses over several statements ("\\boxed{3}. Hmm, maybe \\boxed{4}") earns nothing either: the
last one is the answer.

Normalisation: math delimiters (`$`, `$$`, `\\(`, `\\)`, `\\[`, `\\]`), `\\left`/`\\right`,
`\\displaystyle`, `\\text{}`/`\\mathrm{}`/`\\textbf{}`/`\\mbox{}` (content kept), `\\dfrac`/`\\tfrac`/
`\\cfrac` (= `\\frac`, also `\\frac12`), `\\sqrt{}`/`\\sqrt[n]{}`/`\\sqrt2`, `\\pi`, `\\cdot`, `\\times`,
`\\div`, `\\infty`, degrees (`^\\circ`), markdown bold, unicode (minus signs, `×`, `÷`, `√`, `π`,
`∞`, `≤`, `≥`, `±`, superscripts, vulgar fractions), percentages (`%`, `\\%`, "percent"),
thousands separators (`1,234,567`, `1{,}234`, `1\\,234`, `1 234`; never inside a tuple when the
gold is a tuple/set, and "1,2" is always a list), scientific notation (`1e3`, `1.5 \\times 10^{3}`),
mixed numbers (`2\\frac{1}{2}` = 5/2), leading words ("approximately 5", "I think it's 5") and trailing units
or words ("5 apples", "$5", "5 cm", "5 m/s"; a single letter is read as a unit only when the gold
has no variables and the letter is not x, y, z, n or k). A leading negation ("not 5") makes the
answer unparseable (see Negations). `{6 \\choose 3}` is `\\binom{6}{3}`; `\\sqrt[n]{x}` of a negative
number with n odd is the real root (`\\sqrt[3]{-8}` = -2).

Number words: "nine", "forty-two", "forty two", "two thousand", "one hundred and five", "a
hundred", "minus five", "three point five", fractions "two thirds", "three quarters", "one and a
half", and digits with a scale word ("2.5 million") are numbers. Not when the number word is a
pronoun or quantifier: "one" alone only right after "is", "=", "be", "equals", "exactly",
"about", ... or first in the answer ("the larger one" is not 1); none after "the", "these",
"all", "both", "each", "every", "no", ... ("the two numbers"), nor before "of" ("one of the
roots"). A gold written in number words is a number.

Repeating decimals: `1.\\overline{45}` = 16/11, `0.\\overline{3}`, `0.1\\dot{6}`, `0.\\dot{1}4285\\dot{7}`,
`0.(3)`, and a block repeated at least twice before "..." / `\\ldots` / `\\dots` ("0.333...",
"0.4545...", "0.1666...") are exact fractions; "3.14159..." (no repetition) is the truncated
decimal as written.

Matrices and vectors: `pmatrix`, `bmatrix`, `Bmatrix`, `matrix`, `smallmatrix` and `array` (inside
`\\left( \\right)` or `\\left[ \\right]`) are matrices, compared entrywise with the same shape; a
row or column vector also equals the tuple of its entries (`(1, 2)` or `\\langle 1, 2 \\rangle` for
a pmatrix column); `\\mathbf{v} = \\begin{pmatrix}...` is its right-hand side. A row vector is not a
column vector; a flattened tuple is not a matrix. `vmatrix` (a determinant) is "unparseable answer".

Equivalence: exact rationals (0.5 == 1/2 == 50%); a relative tolerance `rel_tol` (default 1e-6)
applies only when one side is inexact (written with decimals or scientific notation), so
1000000 != 1000001 while 0.3333333 == 1/3; exact irrational forms must agree to 20 digits.
Symbolic answers are equal when sympy proves `a - b == 0` (expand) or both sides agree at seeded
points at 40-digit precision (a probabilistic identity test), with `simplify` deciding when too
few points are usable. The two sides may have different free symbols (`\\cosh^2 u - \\sinh^2 u` is
the constant 1): points cover the union. Points respect domains: a point counts only where both
sides are defined and real, with every square root, fractional power, log, arcsin/arccos/arcosh/
artanh argument in its real domain (complex-valued answers, with `i`, compare complex values);
at least 3 and up to 6 valid points out of up to 24 candidates, and one valid point where they
differ refutes the identity. The candidates mix signs (every sign pattern of the first four
variables), small and larger magnitudes, and are never integers; for one variable the points
between and beyond the real roots of each `|.|`, root, power or log argument come first. So
`\\sqrt{t^2}` is not `t` and `|t|` is not `t` (they differ at negative t), `|(x+5)(x+7)|` is not
`(x+5)(x+7)` (they differ on (-7, -5)), while `\\log(x^2)` equals `2\\log x` and `\\sqrt{x}\\sqrt{y}`
equals `\\sqrt{xy}` where both sides are defined. All sympy work runs under a budget counted in Python function calls
(`symbolic_budget`, default 1e6 calls, well under a second), so a pathological expression ends
as "comparison budget exceeded" instead of a hang (deterministic up to sympy's internal caches,
which only make a repeated comparison cheaper). Sets (`\\{1,2\\}`, bare lists "1, 2") are order-insensitive; tuples `(1, 2, 3)` are
ordered; `(a, b)` is both a pair and an open interval; intervals `(1, 2]`, `[0, \\infty)` and unions
`\\cup` compare endpoints and openness; one-variable inequalities (`x > 3`, `1 < x \\le 2`) are read
as intervals. Equations: `x = 3` vs `3` compares the right-hand side (the last one of a chain
`a = b = 5`); two general equations are equal when `lhs - rhs` agree up to a non-zero constant
factor. A singleton set equals its element. Text answers (`\\text{Evelyn}`) compare
case-insensitively after removing spaces and punctuation.

Percent: when exactly one side is written with a percent sign, p% matches p or p/100 on the
other side (gold "25%" accepts 25, 0.25, 1/4); when both are, the numbers must match.

Closed forms (default): a constant expression is evaluated and compared by value, as a careful
grader does: `2+3`, `4!`, `\\binom{6}{3}`, `\\log_3 9`, `\\sqrt[4]{16}`, `y = 1 + 4` and
`\\frac{3}{-4}` are accepted for 5, 24, 20, 2, 2, 5 and -3/4.
Strict mode, `require_simplified=True` (`get_verifier("math", require_simplified=True)`, or
`-o require_simplified=true` on the command line; `allow_unevaluated=False` is the old spelling):
when the gold is a plain rational number (integer, decimal, fraction), a prediction with a
rational value must be written as a number literal too (integer, decimal, a/b, \\frac{a}{b} with a
sign on either part, mixed number, m x 10^k, a repeating decimal, number words, with an optional
percent sign): `\\boxed{123 \\times 456}` for 56088 is "unevaluated expression" (score 0), for
recipes that train arithmetic and do not want the model to learn to restate the question.
Irrational forms (`\\pi` for 3.14159265) are compared numerically in both modes.

Hard limits on model output (checked before any sympy work): an extracted answer over 1000
characters, a power over 4000 digits (`9^{9^{9^9}}`), a factorial over 3000!, more than 64
list items or 4 `\\pm` signs is "unparseable answer". The verifier never evaluates model text
with `eval`: answers go through our own tokenizer and parser and are built into sympy objects
directly. The runner (verifiers/runner.py) adds the wall-clock limit around all of this.

huggingface/Math-Verify is the reference we compared against. Where we agree: `\\boxed` first
then answer phrases then plain numbers/LaTeX, rightmost match wins within a priority, thousands
separators, `\\frac13`/`\\sqrt3`, `\\text{}` units, `k = 1/3` counts as 1/3, percent handling,
adjacent answers joined by and/or/commas form a set, intervals are open/closed sensitive,
matrices compare entrywise, closed-form constants (`\\binom{6}{3}`, `4!`) count by value (our default).
Where we deliberately differ (and why):
- Math-Verify reads `$3$ or $4$` as the set {3, 4}, and its verify() succeeds when any parsed
  candidate matches; we refuse a multi-valued statement against a single-valued gold
  ("multiple answers"), because accepting it rewards hedging.
- Math-Verify accepts `\\pm 2021` for 2021 (its issue #14); we read `\\pm` as two values.
- Math-Verify rounds floats to 6 decimals and so equates 1/2004! and 1/2006! (issue #14); we use
  a relative tolerance and only when a side is inexact.
- Math-Verify's timeout uses signal.alarm (main thread only); we use a deterministic call budget
  inside and the runner's worker processes outside, so scoring works from any thread.
- We honour `<answer>` tags and `</think>` as scopes, and retractions after the answer.
- With `require_simplified=True` we reject unevaluated arithmetic for a plain-number gold (see
  above); Math-Verify accepts it, and so does our default.
- We do not read a decimal comma ("1,5" is the list 1, 5, not 1.5): a list is far more common.
- We read number words ("forty-two", "two thirds") in an explicit answer, because people write
  them; Math-Verify's extraction targets are LaTeX and plain expressions, not words.
- In prose, "4!" (the "!" right after a digit) is the factorial 24, not the exclamation "4": a
  careful grader cannot tell them apart and the other reading rewarded writing n! for n.
- A negated restatement ("it isn't 8; it's 9") is a retraction too, and a number right after
  "not" is never the answer (an extension of the retraction rule above): a careful grader reads
  "it's 9, not 8" as 9.

Layout (this package; the policy above is the reference the modules point to):
- `extract.py`: the extraction policy (scope, rules, last statement, retractions).
- `normalize.py`: surface clean-up (LaTeX, unicode, percent, thousands separators, number words,
  repeating decimals, matrix environments) and our own tokenizer and parser (text -> node tuples,
  never `eval`; trailing units and words).
- `values.py`: nodes -> values (exact rationals without sympy, sympy objects built under the
  size guards, matrices) and the parsed gold answer.
- `equivalence.py`: comparing a prediction to the gold (tolerance, sympy identity tests with
  domain-aware sample points, sets/tuples/intervals/equations/matrices, the "unevaluated
  expression" and "multiple answers" rules).
- `guards.py`: hard limits on model output and the deterministic sympy call budget.
- `verifier.py`: `MathVerifier`, the seeded audit problems (27 answer kinds) and the
  adversarial audit cases for each kind of gold.
"""
from __future__ import annotations

from posttrain.verifiers.math_answer.extract import Extraction, extract_answer
from posttrain.verifiers.math_answer.extract import _match_brace  # noqa: F401  (verifiers/format.py imports it from here)
from posttrain.verifiers.math_answer.guards import (
    DEFAULT_BUDGET, MAX_ANSWER_CHARS, MAX_DIGITS, MAX_FACTORIAL, MAX_ITEMS, MAX_PM, Unparseable,
)
from posttrain.verifiers.math_answer.normalize import clean_answer, parse_answer_text, tokenize
from posttrain.verifiers.math_answer.values import (
    Gold, Interval, IntervalUnion, Matrix, Relation, Scalar, Seq, Text, build_value, parse_gold,
)
from posttrain.verifiers.math_answer.verifier import MathVerifier, audit_problems

__all__ = [
    "MathVerifier", "audit_problems", "extract_answer", "Extraction", "clean_answer", "tokenize",
    "parse_answer_text", "build_value", "parse_gold", "Gold", "Scalar", "Seq", "Interval", "IntervalUnion", "Matrix",
    "Relation", "Text", "Unparseable", "MAX_ANSWER_CHARS", "MAX_DIGITS", "MAX_FACTORIAL", "MAX_ITEMS",
    "MAX_PM", "DEFAULT_BUDGET",
]
