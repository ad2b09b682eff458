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
"""
from __future__ import annotations

import json
from typing import Sequence

from posttrain.errors import ModelError

_HEADER_START = "{#- posttrain:system_prompt -#}"
_HEADER_END = "{#- /posttrain:system_prompt -#}"


def render_prompt(tokenizer, prompt: str) -> str:
    """The text the model is prompted with: the chat template around `prompt` (the user turn), ending with
    the assistant header; `prompt` itself when the tokenizer has no template."""
    if getattr(tokenizer, "chat_template", None) is None:
        return prompt
    try:
        return tokenizer.apply_chat_template([{"role": "user", "content": prompt}], tokenize=False,
                                             add_generation_prompt=True)
    except Exception as e:  # a Jinja error or a template that refuses these messages
        raise ModelError(f"the chat template of the tokenizer in {tokenizer.name_or_path!r} failed to render a "
                         f"prompt ({type(e).__name__}: {e}); fix the template or set model.chat_template=off") from None


def encode_prompts(tokenizer, prompts: Sequence[str]) -> list[list[int]]:
    """Token ids of each prompt as the model sees it: rendered, then tokenized without the tokenizer's own
    special tokens (the template writes its BOS); plain prompts with them, as before."""
    prompts = list(prompts)
    if not prompts:
        return []
    if getattr(tokenizer, "chat_template", None) is None:
        return [list(x) for x in tokenizer(prompts, add_special_tokens=True)["input_ids"]]
    texts = [render_prompt(tokenizer, p) for p in prompts]
    return [list(x) for x in tokenizer(texts, add_special_tokens=False)["input_ids"]]


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
