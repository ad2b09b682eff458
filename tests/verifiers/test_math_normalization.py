"""Normalisation of extracted answers: each LaTeX / unicode / number-format rule, with a counter-case."""
import pytest

from verifiers.math_answer import MathVerifier, clean_answer

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
    pytest.param("The answer is 5!", "5", id="exclamation-is-punctuation"),
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
