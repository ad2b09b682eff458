"""Chat templates: how a task's prompt becomes the text a (chat) model is prompted with.

Tasks write plain prompts ("Summarize: ..."), and rows, data files, preference pairs and rollout
records keep them plain (so they stay portable between models). The model's own format is applied in
one place: `encode_prompts`, where prompt text becomes token ids. SFT, the reward model, DPO, PPO,
GRPO, the rollout engine (so every sample and evaluation) and reward-model scoring all tokenize
prompts through it, so they all see the same rendered prompt.

Details and choices:
- Rendering (`render_prompt`): `tokenizer.apply_chat_template([{"role": "user", "content": prompt}],
  tokenize=False, add_generation_prompt=True)`: the prompt is the user turn and the text ends with the
  assistant header, so the completion is the assistant's reply.
- When (`model.chat_template`): "auto" renders when the tokenizer has a chat template (a real instruct
  checkpoint); the tokenizers of the presets have none, so nothing changes for them. "on" is "auto" that
  stops with an error naming the model directory when there is no template. "off" never renders: the
  template is removed from the tokenizer.
- BOS: a rendered prompt is tokenized with `add_special_tokens=False`, as `apply_chat_template(...,
  tokenize=True)` does: a template that wants a BOS writes it (`{{ bos_token }}`, Llama 3's
  `<|begin_of_text|>`), and the tokenizer's own BOS would make it two. A plain prompt keeps
  `add_special_tokens=True` (the tokenizer's BOS when it adds one), as before.
- End of turn: completions end with `tokenizer.eos_token` (the trainers append it) and generation stops
  at it (and at `generation_config.eos_token_id`). Instruct checkpoints set eos to their end-of-turn token
  (Qwen2.5-Instruct: `<|im_end|>`). When the template closes an assistant turn with something else (a base
  checkpoint that ships a chat template, e.g. eos `<|endoftext|>` but turns closed by `<|im_end|>`), a note
  says so: the model then learns to stop with eos, not as the template says.
- Persistence: the choice is made on the tokenizer object, so it is saved with every stage's `final/`:
  "off" saves no template, and `model.system_prompt` is written into the template as a default system
  message (a marked header that a later stage replaces, never stacks). Later stages, reward-model scoring,
  `posttrain eval` and any outside tool that loads `final/` then prompt the model as it was trained.
  `system_prompt` null keeps what the directory's template already says; "" removes a posttrain header.

Conversations (rows whose prompt is a list of messages, `{"role", "content"}`, as TRL and the hub's chat
datasets write them):
- A prompt is text or a conversation (`Prompt`). `render_prompt` / `encode_prompts` take either: a
  conversation is rendered as it is (its system message, earlier turns), ending with the assistant header.
  A conversation needs a chat template: without one it is a ModelError (a preset gets one of its own, below).
- `encode_conversation` tokenizes a whole conversation for SFT and says which tokens are the assistant's:
  it renders the first k messages for each assistant turn k (with and without the generation prompt) and
  requires each rendering to be a prefix of the next (templates that rewrite earlier turns, e.g. ones that
  drop past reasoning, are refused with a ModelError: their assistant tokens cannot be located this way).
  An assistant turn is trained from its first token to its eos token included (what follows the eos, e.g.
  ChatML's newline, is context). The prompt (everything before the last reply) is tokenized whole, so its
  tokens are exactly what `encode_prompts` gives for the same messages at generation time, and the earlier
  replies are the tokens that overlap them (the offsets of a fast tokenizer); the last reply is tokenized on
  its own, as a plain completion is. TRL's
  `assistant_only_loss` needs `{% generation %}` markers in the template instead; this works with templates
  as they ship.
- `PRESET_CHAT_TEMPLATE`: the template of a preset built from scratch for conversational data (or
  `model.chat_template=on`): `<|user|>`, `<|assistant|>`, `<|system|>`, `<|tool|>` are special tokens of the
  locally trained tokenizer, each message is its role marker then its content, and an assistant turn ends
  with the eos token.
"""
from __future__ import annotations

import json
from typing import Any, Sequence, Union

from posttrain.errors import ModelError

Message = dict[str, Any]  # {"role": "system" | "user" | "assistant" | "tool", "content": str, ...}
Prompt = Union[str, list[Message]]  # plain text (the user turn) or a conversation
ROLES = ("system", "user", "assistant", "tool")
ROLE_TOKENS = tuple(f"<|{role}|>" for role in ROLES)  # special tokens of a preset's chat template
PRESET_CHAT_TEMPLATE = (
    "{%- for message in messages -%}"
    "{{ '<|' + message['role'] + '|>' + message['content'] }}"
    "{%- if message['role'] == 'assistant' %}{{ eos_token }}{% endif -%}"
    "{%- endfor -%}"
    "{%- if add_generation_prompt %}{{ '<|assistant|>' }}{% endif -%}"
)

_HEADER_START = "{#- posttrain:system_prompt -#}"
_HEADER_END = "{#- /posttrain:system_prompt -#}"


def is_conversation(value: Any) -> bool:
    """`value` is a conversation (a non-empty list of message objects) rather than text."""
    return isinstance(value, (list, tuple)) and len(value) > 0 and all(isinstance(m, dict) for m in value)


def messages_problem(value: Any) -> str | None:
    """What is wrong with `value` as a list of chat messages, or None when it is one."""
    if not isinstance(value, (list, tuple)):
        return f"expected text or a list of messages, got {type(value).__name__}"
    if not value:
        return "an empty list of messages"
    for i, m in enumerate(value, start=1):
        if not isinstance(m, dict):
            return f"message {i}: expected an object with 'role' and 'content', got {type(m).__name__}"
        role = m.get("role")
        if role not in ROLES:
            return f"message {i}: role {role!r} is not one of {', '.join(ROLES)}"
        content = m.get("content")
        if not isinstance(content, str):
            got = "a list of content parts (only text content is supported)" if isinstance(content, list) \
                else type(content).__name__
            return f"message {i} ({role}): 'content' must be text, got {got}"
        if not content.strip():
            return f"message {i} ({role}): empty content"
    return None


def prompt_text(prompt: Prompt) -> str:
    """A prompt as readable text (logs, samples, reports): itself, or its messages as `[role] content` lines."""
    if isinstance(prompt, str):
        return prompt
    return "\n".join(f"[{m['role']}] {m['content']}" for m in prompt)


def prompt_key(prompt: Prompt) -> str:
    """A hashable key of a prompt (text, or a conversation as canonical JSON): equal keys, equal prompts."""
    return prompt if isinstance(prompt, str) else json.dumps(list(prompt), sort_keys=True, ensure_ascii=False)


def _no_template(tokenizer) -> ModelError:
    return ModelError(f"a prompt is a conversation (a list of messages) but the tokenizer in {tokenizer.name_or_path!r} "
                      "has no chat template to render it (or model.chat_template=off); use a model with a chat "
                      "template, or for a preset built from scratch set model.chat_template=on (it then gets one)")


def _apply(tokenizer, messages: Sequence[Message], generation_prompt: bool) -> str:
    try:
        return tokenizer.apply_chat_template(list(messages), tokenize=False, add_generation_prompt=generation_prompt)
    except Exception as e:  # a Jinja error or a template that refuses these messages
        raise ModelError(f"the chat template of the tokenizer in {tokenizer.name_or_path!r} failed to render a "
                         f"prompt ({type(e).__name__}: {e}); fix the template or set model.chat_template=off") from None


def render_prompt(tokenizer, prompt: Prompt) -> str:
    """The text the model is prompted with: the chat template around `prompt` (text: the user turn; a
    conversation: its messages), ending with the assistant header; text itself when there is no template."""
    if getattr(tokenizer, "chat_template", None) is None:
        if isinstance(prompt, str):
            return prompt
        raise _no_template(tokenizer)
    messages = [{"role": "user", "content": prompt}] if isinstance(prompt, str) else prompt
    return _apply(tokenizer, messages, True)


def encode_prompts(tokenizer, prompts: Sequence[Prompt]) -> list[list[int]]:
    """Token ids of each prompt as the model sees it: rendered, then tokenized without the tokenizer's own
    special tokens (the template writes its BOS); plain prompts with them, as before."""
    prompts = list(prompts)
    if not prompts:
        return []
    if getattr(tokenizer, "chat_template", None) is None:
        if not all(isinstance(p, str) for p in prompts):
            raise _no_template(tokenizer)
        return [list(x) for x in tokenizer(prompts, add_special_tokens=True)["input_ids"]]
    texts = [render_prompt(tokenizer, p) for p in prompts]
    return [list(x) for x in tokenizer(texts, add_special_tokens=False)["input_ids"]]


def encode_conversation(tokenizer, messages: Sequence[Message], train_from: int = 0
                        ) -> tuple[list[int], list[int], list[tuple[int, int]]]:
    """A conversation ending with an assistant turn, tokenized for SFT (see the module docstring):
    (prompt_ids, completion_ids, trained) where the completion is the last assistant turn through its eos
    (appended when the template writes none) and `trained` lists the (start, end) token spans of the
    earlier assistant turns at index >= `train_from`, inside prompt_ids."""
    messages = list(messages)
    if getattr(tokenizer, "chat_template", None) is None:
        raise _no_template(tokenizer)
    if not messages or messages[-1].get("role") != "assistant":
        raise ValueError("encode_conversation: the conversation must end with an assistant turn")  # data checks it
    full = _apply(tokenizer, messages, False)
    eos = tokenizer.eos_token or ""
    turns = []  # (start, end) character spans of trained assistant turns in `full`
    for i, m in enumerate(messages):
        if m["role"] != "assistant" or (i < train_from and i != len(messages) - 1):
            continue
        head = _apply(tokenizer, messages[:i], True) if i else ""
        turn = _apply(tokenizer, messages[:i + 1], False)
        if not (turn.startswith(head) and full.startswith(turn)):
            raise ModelError(f"the chat template of the tokenizer in {tokenizer.name_or_path!r} does not render this "
                             f"conversation turn by turn (the first {i + 1} messages do not render as a prefix of the "
                             "whole), so its assistant tokens cannot be located; use a template that keeps earlier "
                             "turns as they are, or rows with one assistant reply (prompt / completion)")
        at = turn.find(eos, len(head)) if eos else -1
        turns.append((len(head), at + len(eos) if at != -1 else len(turn)))
    (last_start, last_end), earlier = turns[-1], turns[:-1]
    prompt, trained = _tokens_with_spans(tokenizer, full[:last_start], earlier)
    completion = tokenizer(full[last_start:last_end], add_special_tokens=False)["input_ids"]
    if not completion or completion[-1] != tokenizer.eos_token_id:
        completion = completion + [tokenizer.eos_token_id]  # as plain completions: generation stops at eos
    return list(prompt), list(completion), trained


def _tokens_with_spans(tokenizer, text: str, spans: list[tuple[int, int]]) -> tuple[list[int], list[tuple[int, int]]]:
    """`text` tokenized whole (as `encode_prompts` does) and the token spans that overlap the character `spans`."""
    if not spans:
        return tokenizer(text, add_special_tokens=False)["input_ids"], []
    enc = tokenizer(text, add_special_tokens=False, return_offsets_mapping=True)
    hit = [any(a < e and s < b for a, b in spans) for s, e in enc["offset_mapping"]]
    out, run = [], None
    for k, h in enumerate(hit + [False]):
        if h and run is None:
            run = k
        elif not h and run is not None:
            out.append((run, k))
            run = None
    return enc["input_ids"], out


def configure(tokenizer, mode: str = "auto", system_prompt: str | None = None, where: str | None = None,
              say=print):
    """Apply `model.chat_template` (auto | on | off) and `model.system_prompt` to `tokenizer` in place
    (see the module docstring); returns it. `where`: the model directory, for the error messages."""
    where = where or tokenizer.name_or_path
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"chat template mode must be auto, on or off, got {mode!r}")  # config checks it first
    if mode == "off":
        if system_prompt:
            raise ModelError("model.system_prompt is set but model.chat_template=off: a system prompt needs the "
                             "chat template; set chat_template=auto or drop system_prompt")
        tokenizer.chat_template = None
        return tokenizer
    template = tokenizer.chat_template
    if template is None:
        if mode == "on":
            raise ModelError(f"model.chat_template=on but the tokenizer in {where!r} has no chat template; point "
                             "model.path at an instruct checkpoint or set model.chat_template=auto/off")
        if system_prompt:
            raise ModelError(f"model.system_prompt is set but the tokenizer in {where!r} has no chat template to "
                             "put it in; drop system_prompt or use a model with a chat template")
        return tokenizer
    if system_prompt is not None:
        if not isinstance(template, str):
            raise ModelError(f"model.system_prompt: the tokenizer in {where!r} has several named chat templates; "
                             "a system prompt needs a single one")
        tokenizer.chat_template = with_system_prompt(template, system_prompt)
    render_prompt(tokenizer, "Hello")  # a template that cannot render stops here, before any training
    note = end_of_turn_note(tokenizer)
    if note:
        say(f"[posttrain] note: {where}: {note}")
    return tokenizer


def with_system_prompt(template: str, system_prompt: str) -> str:
    """`template` that starts the conversation with `system_prompt` when it has no system message ("":
    `template` without an earlier posttrain system prompt)."""
    start = template.find(_HEADER_START)
    end = template.find(_HEADER_END)
    if start != -1 and end != -1:
        template = template[:start] + template[end + len(_HEADER_END):]
    if not system_prompt:
        return template
    # A JSON string is a valid Jinja string literal (Jinja unescapes \" \\ \n like Python).
    literal = json.dumps(system_prompt, ensure_ascii=False)
    header = (f"{_HEADER_START}{{%- if not messages or messages[0]['role'] != 'system' %}}"
              f"{{%- set messages = [{{'role': 'system', 'content': {literal}}}] + messages %}}"
              f"{{%- endif %}}{_HEADER_END}")
    return header + template


def end_of_turn_note(tokenizer) -> str | None:
    """None when the template closes an assistant turn with the eos token (what the trainers append), else
    a one-line note saying what it uses instead."""
    eos = tokenizer.eos_token
    marker = "POSTTRAIN_END_OF_TURN_PROBE"
    try:
        text = tokenizer.apply_chat_template([{"role": "user", "content": "Hello"},
                                              {"role": "assistant", "content": marker}], tokenize=False)
    except Exception:  # e.g. a template that only renders generation prompts: nothing to compare
        return None
    at = text.rfind(marker)
    if at == -1 or not eos:
        return None
    after = text[at + len(marker):]
    if after.startswith(eos) or after.lstrip().startswith(eos):
        return None
    shown = after[:20] or "(nothing)"
    return (f"the chat template ends an assistant turn with {shown!r} but completions end with the eos token "
            f"{eos!r}; the model learns to stop with {eos!r}. Set eos_token in tokenizer_config.json to the "
            "end-of-turn token, or model.chat_template=off")
