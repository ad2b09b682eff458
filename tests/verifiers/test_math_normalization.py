"""Normalisation of extracted answers: each LaTeX / unicode / number-format rule, with a counter-case."""
import pytest

from posttrain.verifiers.math_answer import MathVerifier, clean_answer

V = MathVerifier()


def score(completion, gold):
    return V.check(completion, gold).score


@pytest.mark.parametrize("pred,gold", [
    pytest.param(r"\boxed{\frac{3}{4}}", "0.75", id="frac"),
    pytest.param(r"\boxed{\dfrac{3}{4}}", "3/4", id="dfrac"),
    pytest.param(r"\boxed{\tfrac{3}{4}}", "3/4", id="tfrac"),
    pytest.param(r"\boxed{\cfrac{3}{4}}", "3/4", id="cfrac"),
    pytest.param(r"\boxed{\frac34}", "3/4", id="frac-short-form"),
    pytest.param(r"\boxed{\sqrt{2}}", r"2^{1/2}", id="sqrt"),
    pytest.param(r"\boxed{\sqrt2}", r"\sqrt{2}", id="sqrt-short-form"),
    pytest.param(r"\boxed{\sqrt[3]{16}}", r"2\sqrt[3]{2}", id="nth-root"),
    pytest.param(r"\boxed{2\pi}", r"2 \cdot \pi", id="pi-cdot"),
    pytest.param(r"\boxed{6 \times 7}", "6*7", id="times"),
    pytest.param(r"\boxed{\left( \frac{1}{3} \right)}", "1/3", id="left-right"),
    pytest.param(r"The answer is $\frac{1}{3}$.", "1/3", id="dollars"),
    pytest.param(r"The answer is \(\frac{1}{3}\).", "1/3", id="inline-parens"),
    pytest.param(r"The answer is \[\frac{1}{3}\]", "1/3", id="display-brackets"),
    pytest.param(r"\boxed{5 \text{ cm}}", "5", id="text-units"),
    pytest.param(r"\boxed{\text{5}}", "5", id="text-number"),
    pytest.param(r"\boxed{\mathrm{12}}", "12", id="mathrm"),
    pytest.param(r"\boxed{90^\circ}", "90", id="degrees"),
    pytest.param("The answer is 90\u00b0.", "90", id="degree-sign"),
    pytest.param(r"\boxed{25\%}", "25\\%", id="percent-latex"),
    pytest.param("The answer is 25%.", "0.25", id="percent-to-fraction"),
    pytest.param("The answer is 25 percent.", "1/4", id="percent-word"),
    pytest.param("#### 1,234,567", "1234567", id="thousands-commas"),
    pytest.param(r"\boxed{1{,}234}", "1234", id="thousands-braces"),
    pytest.param(r"\boxed{1\,234}", "1234", id="thousands-thin-space"),
    pytest.param("The answer is 1 234 567.", "1234567", id="thousands-spaces"),
    pytest.param("The answer is 5 apples.", "5", id="trailing-words"),
    pytest.param("The answer is $5.", "5", id="currency-dollar"),
    pytest.param(r"The answer is \$5.", "5", id="currency-escaped"),
    pytest.param("The answer is 5 cm.", "5", id="unit-cm"),
    pytest.param("The answer is 5 m/s.", "5", id="unit-letters"),
    pytest.param("The answer is x = 5 m.", "5", id="equation-with-unit"),
    pytest.param("The answer is approximately 5.", "5", id="leading-filler"),
    pytest.param("The answer is \u22125.", "-5", id="minus-sign-u2212"),
    pytest.param("The answer is \u20135.", "-5", id="en-dash-minus"),
    pytest.param("The answer is 1e3.", "1000", id="scientific-e"),
    pytest.param("The answer is 1.5E-3.", "0.0015", id="scientific-negative"),
    pytest.param(r"The answer is $1.5 \times 10^{3}$.", "1500", id="scientific-times"),
    pytest.param(r"\boxed{2\frac{1}{2}}", "5/2", id="mixed-number"),
    pytest.param("The answer is **42**.", "42", id="markdown-bold"),
    pytest.param("The answer is \u00bd.", "1/2", id="vulgar-fraction"),
    pytest.param("The answer is x\u00b2 + 1.", "x^2+1", id="superscript"),
    pytest.param("The answer is 2\u221a3.", r"2\sqrt{3}", id="root-sign"),
    pytest.param("The answer is 5 apples!", "5", id="exclamation-after-a-word-is-punctuation"),
    pytest.param("The answer is $5$!", "5", id="exclamation-after-math-is-punctuation"),
    pytest.param("The answer is 5 !", "5", id="exclamation-after-a-space-is-punctuation"),
    pytest.param("Janet makes $18!", "18", id="exclamation-after-an-amount-is-punctuation"),
    pytest.param("The answer is 42!!!", "42", id="three-exclamations-are-punctuation"),
])
def test_equivalent_after_normalisation(pred, gold):
    v = V.check(pred, gold)
    assert v.score == 1.0, v


@pytest.mark.parametrize("pred,gold", [
    pytest.param(r"\boxed{1,2}", "12", id="comma-list-is-not-thousands"),
    pytest.param(r"\boxed{1,23}", "123", id="short-group-not-thousands"),
    pytest.param("The answer is 5 apples.", "6", id="units-do-not-help-wrong"),
    pytest.param("The answer is 5x.", "5", id="variable-is-not-a-unit"),
    pytest.param("The answer is not 5.", "5", id="negation"),
    pytest.param(r"\boxed{3\frac{1}{2}}", "3/2", id="mixed-number-is-not-product"),
    pytest.param(r"\boxed{90^\circ}", "91", id="degrees-wrong"),
])
def test_normalisation_does_not_overreach(pred, gold):
    assert score(pred, gold) == 0.0


def test_tuple_keeps_commas_when_gold_is_a_tuple():
    assert score(r"\boxed{(1,234)}", "(1, 234)") == 1.0
    assert score(r"\boxed{1,234}", "1234") == 1.0


def test_clean_answer_examples():
    assert clean_answer(r"\left( \dfrac{1}{2} \right)") == r"( \frac{1}{2} )"
    assert clean_answer(r"$\text{5 apples}$.") == "5 apples"
    assert clean_answer("1,234,567") == "1234567"
    assert clean_answer("1,234,567", merge_thousands=False) == "1,234,567"
    assert clean_answer("\u22123 \u00d7 2") == r"-3 \times 2"


# ------------------------------------------------------------------ factorials (the "!" reward hack)
@pytest.mark.parametrize("completion,gold,expected", [
    pytest.param(r"\boxed{4!}", "4", 0, id="boxed-factorial-is-not-its-argument"),
    pytest.param(r"\boxed{4!}", "24", 1, id="boxed-factorial"),
    pytest.param(r"\boxed{(3)!}", "3", 0, id="paren-factorial-is-not-its-argument"),
    pytest.param(r"\boxed{\left(3\right)!}", "6", 1, id="left-right-factorial"),
    pytest.param(r"\boxed{5!!}", "15", 1, id="double-factorial"),
    pytest.param(r"\boxed{5!!}", "5", 0, id="double-factorial-is-not-its-argument"),
    pytest.param(r"\boxed{n!}", "n!", 1, id="symbolic-factorial"),
    pytest.param(r"\boxed{n!}", "n", 0, id="symbolic-factorial-is-not-n"),
    pytest.param("The answer is 4!", "4", 0, id="prose-factorial-after-digit-is-not-4"),
    pytest.param("The answer is 4!", "24", 1, id="prose-factorial-after-digit"),
    pytest.param("#### 5!", "120", 1, id="hashes-factorial"),
    pytest.param("<answer>3!</answer>", "3", 0, id="tag-factorial-is-not-its-argument"),
    pytest.param("The number of orders is 4!", "4", 0, id="last-number-factorial-is-not-its-argument"),
    pytest.param("There are 4! = 24 ways.", "24", 1, id="factorial-then-value"),
    pytest.param(r"\boxed{5! + 1}", "121", 1, id="factorial-in-an-expression"),
    pytest.param(r"\boxed{\frac{6!}{4!\,2!}}", "15", 1, id="factorials-in-a-fraction"),
])
def test_factorial_is_never_its_argument(completion, gold, expected):
    assert V.check(completion, gold).score == expected


def test_three_bangs_in_math_are_unparseable():
    assert V.check(r"\boxed{5!!!}", "5").reason == "unparseable answer"


# ------------------------------------------------------------------ number words
@pytest.mark.parametrize("completion,gold", [
    pytest.param("The answer is nine.", "9", id="unit"),
    pytest.param("The answer is forty-two.", "42", id="hyphenated"),
    pytest.param("The answer is forty two.", "42", id="spaced"),
    pytest.param("The answer is two thousand.", "2000", id="scale"),
    pytest.param("The answer is one hundred and five.", "105", id="hundred-and"),
    pytest.param("The answer is three hundred twelve thousand four hundred.", "312400", id="long"),
    pytest.param("The answer is a hundred.", "100", id="a-hundred"),
    pytest.param("The answer is minus five.", "-5", id="negative"),
    pytest.param("The answer is two thirds.", "2/3", id="fraction"),
    pytest.param("The answer is one and a half.", "3/2", id="mixed"),
    pytest.param("The answer is 2.5 million.", "2500000", id="digits-with-scale"),
    pytest.param("The answer is one.", "1", id="one-after-is"),
    pytest.param("The answer is Twelve apples.", "12", id="capitalised-with-unit"),
    pytest.param(r"\boxed{\text{seven}}", "7", id="boxed-text"),
    pytest.param("#### eleven", "11", id="hashes"),
    pytest.param("<answer>sixteen</answer>", "16", id="tag"),
    pytest.param("The answer is 9.", "nine", id="gold-in-words"),
    pytest.param("The answer is 'seven'.", "7", id="quoted"),
    pytest.param("The answer is *five*.", "5", id="markdown-italic"),
])
def test_number_words(completion, gold):
    v = V.check(completion, gold)
    assert v.score == 1.0, v


@pytest.mark.parametrize("completion,gold", [
    pytest.param("The answer is forty-three.", "42", id="wrong-value"),
    pytest.param("The answer is the larger one.", "1", id="pronoun-one"),
    pytest.param("The answer is one of the roots.", "1", id="partitive"),
    pytest.param("The answer is the two numbers 3 and 4.", "2", id="quantifier-after-the"),
    pytest.param("Adding the two numbers gives 15.", "2", id="no-words-in-last-number-fallback"),
    pytest.param("The answer is nineteen eighty-four.", "1984", id="year-reading-is-not-a-number"),
])
def test_number_words_do_not_overreach(completion, gold):
    assert V.check(completion, gold).score == 0.0


# ------------------------------------------------------------------ repeating decimals
@pytest.mark.parametrize("pred,gold", [
    pytest.param(r"1.\overline{45}", "16/11", id="overline"),
    pytest.param(r"0.\overline{3}", "1/3", id="overline-one-digit"),
    pytest.param(r"0.1\overline{6}", "1/6", id="overline-after-fixed-digits"),
    pytest.param(r"0.\dot{3}", "1/3", id="dot"),
    pytest.param(r"0.\dot{1}4285\dot{7}", "1/7", id="dots-on-a-block"),
    pytest.param("0.(3)", "1/3", id="parentheses"),
    pytest.param("0.333...", "1/3", id="ellipsis"),
    pytest.param(r"0.4545\ldots", "5/11", id="ldots-block"),
    pytest.param(r"-2.\overline{6}", "-8/3", id="negative"),
    pytest.param(r"0.\overline{9}", "1", id="nines"),
])
def test_repeating_decimals(pred, gold):
    v = V.check(rf"\boxed{{{pred}}}", gold)
    assert v.score == 1.0, v


def test_repeating_decimals_are_exact_and_truncations_are_not():
    assert V.check(r"\boxed{0.\overline{3}}", "0.3334").score == 0.0
    assert V.check("The answer is 0.333...", "1/3").score == 1.0  # the "..." does not end the sentence
    assert V.check(r"\boxed{3.14...}", r"\pi").score == 0.0  # no repetition: 3.14 as written, not pi
    assert V.check(r"\boxed{0.33}", "1/3").score == 0.0


# ------------------------------------------------------------------ thousands separated by spaces
@pytest.mark.parametrize("completion,gold,expected", [
    pytest.param("The factory makes 12 500 parts.", "12500", 1, id="last-number"),
    pytest.param("So the printer makes 41\u00a0170 pages.", "41170", 1, id="no-break-space"),
    pytest.param("So the printer makes 41\u202f170 pages.", "41170", 1, id="narrow-no-break-space"),
    pytest.param("The total is 1 234 567.", "1234567", 1, id="several-groups"),
    pytest.param("The answer is 100 200 300.", "100, 200, 300", 1, id="list-gold-keeps-three-numbers"),
    pytest.param("The factory makes 12 500 parts.", "500", 0, id="not-the-last-group"),
    pytest.param("The values are 3 and 12 50.", "1250", 0, id="short-group-is-not-thousands"),
])
def test_space_thousands_in_plain_text(completion, gold, expected):
    assert V.check(completion, gold).score == expected


def test_choose_is_binomial():
    assert V.check(r"\boxed{{6 \choose 3}}", "20").score == 1.0
