"""Chat templates and conversations: the preset's template, rendering conversational prompts, and SFT's
assistant-only masks checked token by token against the rendered template (posttrain.chat)."""
import pytest

from posttrain.chat import (PRESET_CHAT_TEMPLATE, ROLE_TOKENS, encode_conversation, encode_prompts, prompt_key,
                            prompt_text, render_prompt)
from posttrain.data import collate_completions, tokenize_completions
from posttrain.errors import ModelError
from posttrain.models import train_tokenizer

CORPUS = ["the red fox eats berries", "what is two plus two", "four is the answer", "be brief and kind"] * 40

CONVERSATION = [
    {"role": "system", "content": "Be brief."},
    {"role": "user", "content": "what is two plus two"},
    {"role": "assistant", "content": "four"},
    {"role": "user", "content": "and the red fox?"},
    {"role": "assistant", "content": "it eats berries"},
]

# ChatML as Qwen2.5-Instruct ships it (eos = <|im_end|>, a newline after each turn).
CHATML = ("{% for message in messages %}{{ '<|im_start|>' + message['role'] + '\n' + message['content'] + "
          "'<|im_end|>' + '\n' }}{% endfor %}{% if add_generation_prompt %}{{ '<|im_start|>assistant\n' }}{% endif %}")
# A template whose assistant turns close with a token that is not the eos token.
CLOSES_OTHERWISE = ("{% for message in messages %}{{ '[' + message['role'] + '] ' + message['content'] + "
                    "'<|end|>' }}{% endfor %}{% if add_generation_prompt %}{{ '[assistant] ' }}{% endif %}")
# A template that drops earlier assistant turns (as reasoning templates drop past thinking): not turn by turn.
REWRITES = ("{% for message in messages %}{% if message['role'] != 'assistant' or loop.last %}"
            "{{ '<|' + message['role'] + '|>' + message['content'] }}{% if message['role'] == 'assistant' %}"
            "{{ eos_token }}{% endif %}{% endif %}{% endfor %}{% if add_generation_prompt %}<|assistant|>{% endif %}")


@pytest.fixture(scope="module")
def preset_tok():
    return train_tokenizer(CORPUS, vocab_size=320, chat=True)


def _tok(template, eos="<|eos|>", extra=()):
    tok = train_tokenizer(CORPUS, vocab_size=320)
    if extra:
        tok.add_special_tokens({"additional_special_tokens": list(extra)})
    if eos != "<|eos|>":
        tok.add_special_tokens({"eos_token": eos})
    tok.chat_template = template
    return tok


def _assistant_spans(text: str, messages, eos: str) -> list[tuple[int, int]]:
    """Character spans of each assistant reply and what closes it (`eos`) in the rendered `text`, by search."""
    spans, at = [], 0
    for m in messages:
        at = text.index(m["content"], at)
        if m["role"] == "assistant":
            end = at + len(m["content"])
            if text.startswith(eos, end):
                end += len(eos)
            spans.append((at, end))
        at += len(m["content"])
    return spans


def _check_token_by_token(tok, messages, train_from=0, closer=None):
    """Every token of the conversation is trained iff it overlaps an assistant reply (+ its eos, or the
    template's `closer` of a turn when that is not the eos) of a message at index >= train_from (the last reply
    always), by character position in the rendered template."""
    p, c, trained = encode_conversation(tok, messages, train_from)
    batch = collate_completions([(p, c, trained)], tok.pad_token_id)
    ids, mask = batch["input_ids"][0].tolist(), batch["completion_mask"][0].tolist()
    text = tok.apply_chat_template(messages, tokenize=False)
    spans = _assistant_spans(text, messages, closer or tok.eos_token)
    assistants = [i for i, m in enumerate(messages) if m["role"] == "assistant"]
    wanted = [s for i, s in zip(assistants, spans) if i >= train_from or i == assistants[-1]]
    rebuilt, pos = "", 0
    for k, (t, m) in enumerate(zip(ids, mask)):
        piece = tok.decode([t])
        start = text.find(piece, pos) if piece else pos
        if k == len(ids) - 1 and t == tok.eos_token_id and not text.startswith(piece, pos):
            assert m, "the appended eos is trained"
            continue
        assert start == pos, (k, piece, text[pos:pos + 20])
        inside = any(a < start + len(piece) and start < b for a, b in wanted)  # the token overlaps a reply
        assert bool(m) == inside, (k, repr(piece), m, inside)
        rebuilt += piece
        pos += len(piece)
    return p, c, trained, text, rebuilt


def test_preset_template_role_markers_are_single_special_tokens(preset_tok):
    assert preset_tok.chat_template == PRESET_CHAT_TEMPLATE
    ids = preset_tok.convert_tokens_to_ids(list(ROLE_TOKENS))
    assert ids == [3, 4, 5, 6]  # after pad, eos, bos: the rest of the vocabulary is trained as before
    text = render_prompt(preset_tok, "what is two plus two")
    assert text == "<|user|>what is two plus two<|assistant|>"
    enc = encode_prompts(preset_tok, ["what is two plus two"])[0]
    assert enc[0] == ids[1] and enc[-1] == ids[2]
    assert preset_tok.decode(enc, skip_special_tokens=True) == "what is two plus two"
    plain = train_tokenizer(CORPUS, vocab_size=320)
    assert plain.chat_template is None and len(plain) == len(preset_tok) - 4  # chat=False: the old vocabulary
    assert plain.convert_ids_to_tokens(list(range(7, 40))) == preset_tok.convert_ids_to_tokens(list(range(11, 44)))


def test_conversational_prompt_renders_every_turn(preset_tok):
    prompt = CONVERSATION[:-1]
    assert render_prompt(preset_tok, prompt) == ("<|system|>Be brief.<|user|>what is two plus two<|assistant|>four"
                                                 "<|eos|><|user|>and the red fox?<|assistant|>")
    assert prompt_text(prompt).splitlines()[0] == "[system] Be brief."
    assert prompt_key(prompt) == prompt_key([dict(m) for m in prompt]) != prompt_key(CONVERSATION[:3])
    assert prompt_text("plain") == prompt_key("plain") == "plain"


@pytest.mark.parametrize("kind", ["preset", "chatml", "closes-otherwise"])
def test_assistant_only_mask_matches_the_rendered_template(preset_tok, kind):
    tok = {"preset": lambda: preset_tok,
           "chatml": lambda: _tok(CHATML, eos="<|im_end|>", extra=["<|im_start|>", "<|im_end|>"]),
           "closes-otherwise": lambda: _tok(CLOSES_OTHERWISE, extra=["<|end|>"])}[kind]()
    for train_from in (0, 3):
        p, c, trained, text, rebuilt = _check_token_by_token(tok, CONVERSATION, train_from,
                                                             "<|end|>" if kind == "closes-otherwise" else None)
        assert c[-1] == tok.eos_token_id
        assert len(trained) == (1 if train_from == 0 else 0)
        # the prompt is exactly what generation is prompted with for the same messages
        assert p == encode_prompts(tok, [CONVERSATION[:-1]])[0]
        assert text.startswith(rebuilt)
    if kind == "chatml":
        assert tok.decode(c) == "it eats berries<|im_end|>"  # the newline after the eos is not trained
    if kind == "closes-otherwise":
        assert tok.decode(c) == "it eats berries<|end|><|eos|>"  # eos appended: generation stops at eos


def test_sft_rows_of_both_forms_tokenize_and_collate(preset_tok):
    from posttrain.data import normalize_row

    messages_row, fmt = normalize_row({"messages": CONVERSATION}, "sft")
    assert fmt == "conversational (messages)"
    pc_row, fmt2 = normalize_row({"prompt": CONVERSATION[:3] + CONVERSATION[3:4], "completion": "it eats berries"},
                                 "sft")
    assert fmt2 == "conversational" and pc_row["train_from"] == 4 and pc_row["messages"] == CONVERSATION
    items, dropped = tokenize_completions([messages_row, pc_row, {"prompt": "what is two plus two",
                                                                  "completion": " four"}], preset_tok, 256)
    assert dropped == 0 and len(items[0]) == 3 and len(items[1]) == 2 and len(items[2]) == 2
    batch = collate_completions(items, preset_tok.pad_token_id)
    trained = [preset_tok.decode(batch["input_ids"][i][batch["completion_mask"][i]]) for i in range(3)]
    assert trained == ["four<|eos|>it eats berries<|eos|>", "it eats berries<|eos|>", " four<|eos|>"]
    short, dropped = tokenize_completions([messages_row], preset_tok, 10)
    assert short == [] and dropped == 1


def test_templates_that_rewrite_earlier_turns_are_refused():
    tok = _tok(REWRITES, extra=list(ROLE_TOKENS))
    with pytest.raises(ModelError, match="turn by turn"):
        encode_conversation(tok, CONVERSATION)
    p, c, trained = encode_conversation(tok, CONVERSATION[:3])  # one assistant turn: nothing to rewrite
    assert tok.decode(c) == "four<|eos|>" and trained == []


def test_a_conversation_needs_a_chat_template():
    tok = train_tokenizer(CORPUS, vocab_size=320)
    with pytest.raises(ModelError, match="model.chat_template=on"):
        encode_prompts(tok, [CONVERSATION[:2]])
    with pytest.raises(ModelError, match="no chat template"):
        render_prompt(tok, CONVERSATION[:2])
    with pytest.raises(ModelError, match="no chat template"):
        encode_conversation(tok, CONVERSATION)
    assert encode_prompts(tok, ["plain text"]) == [tok("plain text")["input_ids"]]
