"""Extraction policy of the math verifier: each rule, priorities, last occurrence, scopes, hedges, retractions."""
import pytest

from posttrain.verifiers.math_answer import MathVerifier, extract_answer

V = MathVerifier()


def ext(text):
    e = extract_answer(text)
    return None if e is None else (e.rule, e.parts, e.retracted)


@pytest.mark.parametrize("text,rule,parts", [
    pytest.param(r"so \boxed{42}.", "boxed", ["42"], id="boxed"),
    pytest.param(r"\fbox{7}", "boxed", ["7"], id="fbox"),
    pytest.param(r"\boxed{\frac{1}{\sqrt{2}}}", "boxed", [r"\frac{1}{\sqrt{2}}"], id="boxed-nested-braces"),
    pytest.param(r"\boxed{\{1, 2\}}", "boxed", [r"\{1, 2\}"], id="boxed-escaped-braces"),
    pytest.param(r"\boxed{\boxed{5}}", "boxed", [r"\boxed{5}"], id="boxed-in-boxed-is-one"),
    pytest.param("Thus the answer is 12. Done.", "answer phrase", ["12"], id="the-answer-is"),
    pytest.param("Final answer: 3.5", "answer phrase", ["3.5"], id="final-answer-colon"),
    pytest.param("**Final Answer:** 9", "answer phrase", ["9"], id="markdown-final-answer"),
    pytest.param("The answer is:\n\n$$\\frac{1}{2}$$\nbye", "answer phrase", ["$$\\frac{1}{2}$$"], id="answer-on-next-line"),
    pytest.param("work work\n#### 1,234\n", "####", ["1,234"], id="hashes"),
    pytest.param("<answer>x = 5</answer>", "answer tag", ["x = 5"], id="answer-tag-content"),
    pytest.param("we get 3 and then 17 apples", "last number", ["17"], id="last-number"),
    pytest.param("area is $3\\sqrt{2}$ units", "last number", ["3\\sqrt{2}"], id="last-inline-math"),
    pytest.param("so 7\\sqrt{5} it is", "last number", ["7\\sqrt{5}"], id="last-bare-latex"),
    pytest.param("about 2.9 \\times 10^{4} of them", "last number", ["2.9 \\times 10^{4}"], id="last-scientific"),
])
def test_each_rule(text, rule, parts):
    assert ext(text) == (rule, parts, False)


def test_dollar_signs_as_currency():
    assert V.check(r"So, the total cost is $\$12.50$.", "12.5").score == 1.0
    assert V.check("So, the total cost is $12.50.", "12.5").score == 1.0
    # "$5 and $6": two amounts joined by "and" at the end are a hedge for a single gold
    assert V.check("It costs $5 and $6", "6").reason == "multiple answers"


def test_no_answer():
    assert extract_answer("I have no idea.") is None
    assert extract_answer("") is None
    assert V.check("I have no idea.", "5").reason == "no answer found"


@pytest.mark.parametrize("text,expected_rule,value", [
    pytest.param(r"The answer is 3. \boxed{4}", "boxed", "4", id="boxed-beats-phrase"),
    pytest.param(r"\boxed{4} and later the answer is 3.", "boxed", "4", id="boxed-beats-later-phrase"),
    pytest.param("The answer is 3.\n#### 4", "answer phrase", "3", id="phrase-beats-hashes"),
    pytest.param("#### 4\nthen 99 more", "####", "4", id="hashes-beat-last-number"),
])
def test_priority(text, expected_rule, value):
    e = extract_answer(text)
    assert e.rule == expected_rule and e.parts == [value]


def test_last_occurrence_of_winning_rule_counts():
    assert ext(r"\boxed{3} ... hmm, let me redo it ... \boxed{4}") == ("boxed", ["4"], False)
    text = "The answer is 5. Wait, actually the answer is 6"
    assert ext(text) == ("answer phrase", ["6"], False)
    assert V.check(text, "6").score == 1.0
    assert V.check(text, "5").score == 0.0


@pytest.mark.parametrize("text,gold", [
    pytest.param(r"\boxed{3} or \boxed{4}", "4", id="two-boxes-or"),
    pytest.param(r"\boxed{4}, \boxed{3}", "4", id="two-boxes-comma"),
    pytest.param("$\\boxed{3}$ $\\boxed{4}$", "4", id="two-boxes-in-dollars"),
    pytest.param("the answer is 3, 4, 5 or 6", "4", id="answer-is-list"),
    pytest.param("The answer is 3 or the answer is 4", "4", id="two-phrases-or"),
    pytest.param(r"\boxed{3 \text{ or } 4}", "3", id="or-inside-box"),
    pytest.param(r"\boxed{\pm 3}", "3", id="plus-minus"),
    pytest.param("it is either 8 or 9", "9", id="last-numbers-either-or"),
])
def test_several_candidates_get_no_credit(text, gold):
    v = V.check(text, gold)
    assert v.score == 0.0
    assert v.reason == "multiple answers"


def test_several_candidates_form_a_set_when_gold_has_several_elements():
    assert V.check(r"\boxed{3} or \boxed{4}", "3, 4").score == 1.0
    assert V.check(r"\boxed{3} and \boxed{4}", r"\{4, 3\}").score == 1.0
    assert V.check(r"\boxed{3} and \boxed{5}", r"\{4, 3\}").score == 0.0
    assert V.check("So $x = 2$ or $x = 3$.", "2, 3").score == 1.0


def test_same_value_twice_is_not_a_hedge():
    assert V.check(r"\boxed{1/2} or equivalently \boxed{0.5}", "1/2").score == 1.0
    assert V.check(r"\boxed{\frac{1}{2}}, \boxed{0.5}", "1/2").score == 1.0


def test_spread_out_guesses_only_last_counts():
    # separated by prose: a correction, only the last statement counts
    assert V.check(r"\boxed{3}. Hmm, maybe instead \boxed{4}", "3").score == 0.0
    assert V.check(r"\boxed{3}. Hmm, maybe instead \boxed{4}", "4").score == 1.0


def test_answer_tag_is_the_scope():
    text = "<think>the answer is 3, or \\boxed{3}</think><answer>5</answer> trailing 3"
    assert ext(text) == ("answer tag", ["5"], False)
    assert V.check(text, "5").score == 1.0
    # inside the tag the normal ladder applies
    assert ext("<answer>so \\boxed{7}, not 8</answer>")[:2] == ("boxed", ["7"])
    # the last closed tag counts; an unclosed tag is not a scope
    assert ext("<answer>1</answer><answer>2</answer>")[1] == ["2"]
    assert ext("<answer>1</answer> <answer>2")[:2] == ("answer tag", ["1"])


def test_answer_tag_falls_back_to_last_number_inside():
    assert V.check("<answer>I think it's 12 apples</answer>", "12").score == 1.0


def test_think_block_does_not_count():
    text = "<think>Maybe \\boxed{3}?</think>\nThe answer is 4."
    assert ext(text) == ("answer phrase", ["4"], False)
    # nothing after </think>: fall back to the whole text
    assert ext("<think>so \\boxed{3}</think>") == ("boxed", ["3"], False)


@pytest.mark.parametrize("text,gold,score,reason", [
    pytest.param("The answer is 7. No wait, that's wrong, it's 8.", "7", 0.0, "wrong answer", id="replaced"),
    pytest.param("The answer is 7. No wait, that's wrong, it's 8.", "8", 1.0, "correct", id="replacement-counts"),
    pytest.param(r"\boxed{7} Hmm, that is incorrect. The answer is 8.", "8", 1.0, "correct", id="boxed-retracted"),
    pytest.param("The answer is 7. Scratch that.", "7", 0.0, "answer retracted", id="retracted-nothing-after"),
    pytest.param("<answer>7</answer>\nI made a mistake, it is 9", "9", 1.0, "correct", id="after-tag"),
    pytest.param("<answer>7</answer>\nwait, no.", "7", 0.0, "answer retracted", id="after-tag-nothing"),
    pytest.param(r"\boxed{7}. Note: option C, 9, is wrong.", "7", 1.0, "correct", id="third-person-is-not-retraction"),
])
def test_retractions(text, gold, score, reason):
    v = V.check(text, gold)
    assert (v.score, v.reason) == (score, reason)


def test_huge_outputs_are_handled():
    assert V.check("x" * 1_000_000, "1").reason == "no answer found"
    assert V.check("blah " * 200_000 + "the answer is 42", "42").score == 1.0
    assert V.check(r"\boxed{" * 50_000, "1").score == 0.0
    v = V.check(("7 " * 300_000) + "\\boxed{8}", "8")
    assert v.score == 1.0 and v.details["rule"] == "boxed"


def test_details_are_reported():
    v = V.check(r"so $\boxed{\dfrac{2}{4}}$", "0.5")
    assert v.details == {"rule": "boxed", "extracted": r"\dfrac{2}{4}", "normalized": "1/2", "gold": "1/2"}


# ------------------------------------------------------------------ retractions and negations
@pytest.mark.parametrize("text,gold,score", [
    pytest.param("It isn't 8; it's 9.", "9", 1.0, id="prose-negation-then-answer"),
    pytest.param("It isn't 8; it's 9.", "8", 0.0, id="prose-negated-value-is-not-the-answer"),
    pytest.param("The answer isn't 8; it's 9.", "9", 1.0, id="negated-phrase-then-answer"),
    pytest.param("The answer isn't 8; it's 9.", "8", 0.0, id="negated-phrase-is-not-its-value"),
    pytest.param("I guessed the answer is 5. The answer isn't 8; it's 9.", "9", 1.0, id="negated-phrase-is-the-last-phrase"),
    pytest.param("The answer is not 8; it is 9.", "9", 1.0, id="not-x-semicolon-y"),
    pytest.param("The answer is not 8 but 9.", "9", 1.0, id="not-x-but-y"),
    pytest.param("The answer is not 8. It's 9.", "9", 1.0, id="not-x-next-sentence"),
    pytest.param("The answer: it isn't 8; it's 9.", "9", 1.0, id="inside-the-phrase-value"),
    pytest.param("<answer>It isn't 8; it's 9.</answer>", "9", 1.0, id="inside-the-tag"),
    pytest.param(r"\boxed{8}. Hmm, it isn't 8, it's 9.", "9", 1.0, id="boxed-then-negated-restatement"),
    pytest.param(r"\boxed{8}. Hmm, it isn't 8, it's 9.", "8", 0.0, id="negated-restatement-voids-the-box"),
    pytest.param("The answer is 8. Actually, 8 is wrong; it's 9.", "9", 1.0, id="value-is-wrong"),
    pytest.param("The answer is 2. Hmm, the answer is not 2.", "2", 0.0, id="negated-restatement-nothing-after"),
    pytest.param("The answer is 2. The answer is not 3.", "2", 1.0, id="negating-another-value-keeps-the-answer"),
    pytest.param(r"\boxed{5} Note that it is not 5 in base 10.", "5", 1.0, id="negation-of-something-else"),
    pytest.param(r"\boxed{7}. Note: option 7 is wrong.", "7", 1.0, id="third-person-value-is-not-retraction"),
    pytest.param("It's 9, not 8.", "9", 1.0, id="negated-alternative-after"),
    pytest.param("He is not 30, he is 35.", "35", 1.0, id="negated-alternative-before"),
    pytest.param("Answer: 5 (not 6).", "5", 1.0, id="parenthetical-negation"),
    pytest.param("I first got 16. The answer isn't 16; it's 21.\nNo wait, that's wrong. It's 25.", "25", 1.0,
                 id="retraction-after-the-replacement"),
    pytest.param(r"\boxed{8}. No, it's 9.", "9", 1.0, id="correction-with-a-value"),
    pytest.param(r"\boxed{8}. Wait, actually the answer is 9.", "9", 1.0, id="correction-after-a-box"),
    pytest.param("The answer is 8... no, it's 9.", "9", 1.0, id="correction-after-ellipsis"),
    pytest.param(r"\boxed{8}. Is there another solution? No, it's unique.", "8", 1.0, id="no-without-a-value-is-not-a-correction"),
    pytest.param("I got 7 but 7 is wrong, so 9", "9", 1.0, id="number-before-is-wrong-is-not-a-candidate"),
])
def test_negations_and_negated_restatements(text, gold, score):
    v = V.check(text, gold)
    assert v.score == score, v


# ------------------------------------------------------------------ the last-number rule
@pytest.mark.parametrize("text,gold,score", [
    pytest.param("So the expression factors as (a-2)^2.", "(a-2)^2", 1.0, id="plain-expression"),
    pytest.param("So the expression factors as (a-2)^2.", "2", 0.0, id="plain-expression-is-not-its-exponent"),
    pytest.param("We look for two factors. So it factors as (b + 5)(b - 5).", "b^2-25", 1.0, id="plain-product"),
    pytest.param("The expression simplifies to 2a + 3b.", "2a+3b", 1.0, id="plain-sum"),
    pytest.param("Then 5x = 10, so x = 2.", "2", 1.0, id="numbers-after-an-expression-still-count"),
    pytest.param("The area is 12 cm^2", "12", 1.0, id="exponent-is-not-a-candidate"),
    pytest.param("So the speed is 12 m/s.", "12", 1.0, id="unit-letters-are-not-variables"),
    pytest.param("In the x-y plane the distance is 5.", "5", 1.0, id="hyphenated-letters"),
    pytest.param("Let f(x) = x^2 + 1, so f(2) = 5.", "5", 1.0, id="function-notation"),
    pytest.param("The result is sqrt(x) + 1.", r"\sqrt{x}+1", 1.0, id="plain-function-names"),
    pytest.param("Thus the derivative is 2 * (x + 3).", "2x+6", 1.0, id="plain-product-with-star"),
])
def test_last_number_rule_reads_plain_expressions(text, gold, score):
    v = V.check(text, gold)
    assert v.score == score, v


def test_prose_bang_rules_in_extraction():
    from posttrain.verifiers.math_answer.extract import _prose_bangs

    assert _prose_bangs("4!") == "4!"
    assert _prose_bangs("(n+1)!").strip() == "(n+1)!"
    assert _prose_bangs("5 apples!").strip() == "5 apples"
    assert _prose_bangs("$5$!").strip() == "$5$"
    assert _prose_bangs("$4!$") == "$4!$"
    assert _prose_bangs("x != 3") == "x != 3"
    assert _prose_bangs("12!!!").strip() == "12"
