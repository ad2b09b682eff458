"""The environment protocol: what a multi-turn episode with tools is, in plain Python (no torch).

An `Environment` gives, for a problem row, the first messages and the tools; for each assistant turn it says what
to append (tool results, a user message) or that the episode is over; at the end it gives the reward (and,
optionally, a reward per turn). The rollout engine (`posttrain.rollout.multiturn`) samples the assistant turns,
runs the tool calls (`posttrain.verifiers.envs.runner.ToolRunner`) and appends exactly the tokens the chat template
adds for the environment's messages; this module never sees a token.

    class Calc(Environment):
        name = "calc"
        tools = (calculator,)                        # plain functions with type hints and an Args: docstring
        def reward(self, episode):                   # the final reward, in [0, 1] or any float
            return float(episode.final_text.strip() == str(episode.problem["answer"]))

Tool calls, the default format (`parse_tool_calls`; for chat templates without tools, which are SmolLM2's ChatML
and our presets): the system message lists the tools as JSON schemas (from `transformers.utils.get_json_schema`,
the chat-template `tools=` convention, never written by hand) and the assistant writes each call as

    <tool_call>{"name": "calculator", "arguments": {"expression": "12*34"}}</tool_call>

A result comes back as a message with the `tool` role, whose content is the tool's return value, or
`error: ...` naming what went wrong: a malformed call (not JSON, no name, arguments not an object, or past the
parser's limits below), an unknown tool, bad arguments (the function's signature refuses them), an exception in the
tool, or a timeout. Such errors are counted in the metrics and never stop a step. An assistant turn with no call ends
the episode: its text is the final answer (`Episode.final_text`).

No text raises out of `parse_tool_calls`, and its time is linear in the text's length. A call is malformed, with a
one-line reason, when its JSON is longer than `MAX_CALL_CHARS` characters, nests brackets deeper than
`MAX_CALL_DEPTH` levels (json.loads would raise RecursionError), holds an integer of more than
`MAX_NUMBER_DIGITS` digits (Python refuses int() past 4300 digits), or a string with an unpaired surrogate escape
such as "\\ud800" (no tokenizer or UTF-8 file takes it).

Limits (`Limits`): assistant turns per episode, sampled tokens per turn, tokens in all (sampled and environment,
after the prompt), tool calls per turn, seconds per tool call.
"""
from __future__ import annotations

import inspect
import json
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

CALL_OPEN, CALL_CLOSE = "<tool_call>", "</tool_call>"
MAX_CALL_CHARS = 100_000  # a call's JSON text (the python tool takes code up to 20,000 characters)
MAX_CALL_DEPTH = 100  # brackets nested in a call's JSON (json.loads and json.dumps recurse per level)
MAX_NUMBER_DIGITS = 1000  # digits of an integer in a call's JSON (json.dumps of the episode refuses more than 4300)
_JSON_TOKENS = re.compile(r'\\.|["\[\]{}]', re.DOTALL)  # an escape, a quote or a bracket
ERROR_KINDS = ("malformed", "unknown_tool", "bad_arguments", "exception", "timeout", "too_many_calls")


@dataclass(frozen=True)
class Limits:
    """An episode's limits (checked by the rollout engine and the tool runner)."""

    max_turns: int = 4  # assistant turns per episode; the last one's calls are not run
    max_turn_tokens: int = 96  # sampled tokens per assistant turn (a turn cut here ends the episode: "length")
    max_total_tokens: int = 384  # sampled + environment tokens after the prompt (over it: the episode ends)
    max_calls_per_turn: int = 4  # further calls in one turn are answered "error: too many tool calls"
    tool_timeout_s: float = 5.0  # wall clock per tool call (a hung tool is abandoned: "timeout")

    def __post_init__(self) -> None:
        for name in ("max_turns", "max_turn_tokens", "max_total_tokens", "max_calls_per_turn"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"Limits.{name} must be a positive integer, got {getattr(self, name)!r}")
        if not self.tool_timeout_s > 0:
            raise ValueError(f"Limits.tool_timeout_s must be > 0, got {self.tool_timeout_s!r}")


@dataclass
class ToolCall:
    """One call as the model wrote it; `error` is set when it could not be parsed."""

    name: str | None
    arguments: dict[str, Any] | None
    raw: str
    error: str | None = None  # "malformed: ..." when the text is not a call


@dataclass
class ToolResult:
    """What one call returned: `content` is what the model sees; `error` the kind (ERROR_KINDS) or None."""

    call: ToolCall
    content: str
    error: str | None = None
    seconds: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.call.name, "arguments": self.call.arguments, "raw": self.call.raw,
                "content": self.content, "error": self.error, "seconds": round(self.seconds, 6)}


@dataclass
class Turn:
    """One assistant turn: its text, the calls it made and what they returned, its reward (if the environment
    gives per-turn rewards)."""

    text: str
    results: list[ToolResult] = field(default_factory=list)
    reward: float | None = None
    sampled_tokens: int = 0
    env_tokens: int = 0  # tokens appended after it (tool results, the next assistant header)


@dataclass
class Episode:
    """A problem's conversation as it unfolds (the rollout engine fills it in)."""

    problem: dict[str, Any]
    messages: list[dict[str, Any]]
    turns: list[Turn] = field(default_factory=list)
    finish: str = ""  # "answer" (a turn without calls), "max_turns", "max_tokens", "length" (a turn cut)
    state: dict[str, Any] = field(default_factory=dict)  # the environment's own scratch space

    @property
    def final_text(self) -> str:
        """The last assistant turn's text (the answer when the episode ended with a turn without calls)."""
        return self.turns[-1].text if self.turns else ""

    def tool_results(self) -> list[ToolResult]:
        return [r for t in self.turns for r in t.results]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: finish, turns (text, reward, token counts, tool calls with results), messages."""
        return {"finish": self.finish, "messages": self.messages,
                "turns": [{"text": t.text, "reward": t.reward, "sampled_tokens": t.sampled_tokens,
                           "env_tokens": t.env_tokens, "tool_calls": [r.to_dict() for r in t.results]}
                          for t in self.turns]}


class _Refused(ValueError):
    """JSON that the parser refuses as a tool call although it may be JSON: past a limit, or an unpaired surrogate
    (the message says which)."""


def parse_tool_calls(text: str) -> list[ToolCall]:
    """The calls in an assistant turn, in the default format `<tool_call>{"name": ..., "arguments": {...}}
    </tool_call>`. A block that is not such an object is a call with `error` set (it is answered with the error,
    so the model sees what was wrong). An unclosed `<tool_call>` is a malformed call too, and so is a call past the
    parser's limits (module docstring; its `raw` cut to 200 characters, as an unclosed tag's); no text raises here."""
    calls = []
    blocks, tail = _split_calls(text)
    for raw, body in blocks:
        body = body.strip()
        try:
            obj = _loads(body)
        except _Refused as e:
            calls.append(ToolCall(None, None, raw[:200], f"malformed: {e}"))
            continue
        except json.JSONDecodeError as e:
            calls.append(ToolCall(None, None, raw, f"malformed: not JSON ({e.msg} at character {e.pos})"))
            continue
        if not isinstance(obj, dict) or not isinstance(obj.get("name"), str) or not obj["name"].strip():
            calls.append(ToolCall(None, None, raw, 'malformed: expected {"name": "...", "arguments": {...}}'))
            continue
        args = obj.get("arguments", {})
        if isinstance(args, str):  # some models write the arguments as a JSON string
            try:
                args = _loads(args)
            except _Refused as e:
                calls.append(ToolCall(obj["name"], None, raw[:200], f"malformed: {e}"))
                continue
            except json.JSONDecodeError:
                pass
        if not isinstance(args, dict):
            calls.append(ToolCall(obj["name"], None, raw, "malformed: 'arguments' must be an object"))
            continue
        calls.append(ToolCall(obj["name"].strip(), args, raw))
    if CALL_OPEN in tail:
        calls.append(ToolCall(None, None, tail[tail.index(CALL_OPEN):][:200],
                              "malformed: <tool_call> without </tool_call>"))
    return calls


def _split_calls(text: str) -> tuple[list[tuple[str, str]], str]:
    """The `<tool_call>...</tool_call>` blocks of `text` as (raw, body) pairs, and the text outside them joined. A
    block runs from an opening tag to the first closing tag after it (what the regex `<tool_call>(.*?)</tool_call>`
    matches); found with str.find, because that regex takes quadratic time on a text of many unclosed tags."""
    blocks, outside, i = [], [], 0
    while True:
        start = text.find(CALL_OPEN, i)
        end = text.find(CALL_CLOSE, start + len(CALL_OPEN)) if start >= 0 else -1
        if end < 0:
            outside.append(text[i:])
            return blocks, "".join(outside)
        outside.append(text[i:start])
        blocks.append((text[start:end + len(CALL_CLOSE)], text[start + len(CALL_OPEN):end]))
        i = end + len(CALL_CLOSE)


def _loads(body: str) -> Any:
    """`json.loads(body)` within the parser's limits: json.JSONDecodeError for text that is not JSON, _Refused for
    JSON past a limit or with an unpaired surrogate (module docstring). The limits are checked before or while
    decoding, so no input makes json.loads recurse past `MAX_CALL_DEPTH` or convert a huge integer."""
    if len(body) > MAX_CALL_CHARS:
        raise _Refused(f"tool call longer than {MAX_CALL_CHARS} characters ({len(body)})")
    if body.count("[") + body.count("{") > MAX_CALL_DEPTH and _nesting(body) > MAX_CALL_DEPTH:
        raise _Refused(f"tool call nested deeper than {MAX_CALL_DEPTH} levels")
    obj = json.loads(body, parse_int=_integer)
    try:
        json.dumps(obj, ensure_ascii=False).encode("utf-8")
    except UnicodeEncodeError:
        raise _Refused("tool call holds an unpaired surrogate (an escape such as \\ud800 alone); write the "
                       "character itself") from None
    return obj


def _nesting(body: str) -> int:
    """How deep `[` and `{` nest outside JSON strings in `body`: a JSON text's depth; for other text, at least the
    depth json.loads reaches before it fails (it never reads past the first error)."""
    depth = deepest = 0
    in_string = False
    for m in _JSON_TOKENS.finditer(body):
        token = m.group()
        if token == '"':
            in_string = not in_string
        elif in_string or len(token) == 2:  # a bracket inside a string, or an escape
            continue
        elif token in "[{":
            depth += 1
            deepest = max(deepest, depth)
        else:
            depth -= 1
    return deepest


def _integer(literal: str) -> int:
    """An integer literal of a call's JSON (json.loads' parse_int), refused past `MAX_NUMBER_DIGITS` digits."""
    if len(literal) > MAX_NUMBER_DIGITS + literal.startswith("-"):
        raise _Refused(f"tool call holds a number of more than {MAX_NUMBER_DIGITS} digits")
    return int(literal)


def format_tool_call(name: str, arguments: dict[str, Any]) -> str:
    """The default format of one call (demonstrations, tests): the inverse of `parse_tool_calls`."""
    return "<tool_call>" + json.dumps({"name": name, "arguments": arguments}, separators=(", ", ": ")) + "</tool_call>"


def tool_name(fn: Callable) -> str:
    return getattr(fn, "__name__", type(fn).__name__)


def tool_schema(fn: Callable) -> dict[str, Any]:
    """A tool's JSON schema, from `transformers.utils.get_json_schema` (type hints + an Args: docstring): the
    convention chat templates with `tools=` use. transformers is imported here, on first use only."""
    try:
        from transformers.utils import get_json_schema
    except ImportError as e:  # the verifier layer imports without it; schemas need it
        raise ImportError(f"tool schemas need transformers (transformers.utils.get_json_schema): {e}") from None
    try:
        return get_json_schema(fn)
    except Exception as e:
        raise ValueError(f"tool {tool_name(fn)!r}: no JSON schema ({type(e).__name__}: {e}); give it type hints and "
                         "a docstring with an Args: section describing every argument") from None


def check_arguments(fn: Callable, arguments: dict[str, Any]) -> str | None:
    """Why `fn(**arguments)` cannot be called (a missing or unexpected argument), or None."""
    try:
        inspect.signature(fn).bind(**arguments)
    except TypeError as e:
        return str(e)
    except ValueError:  # no signature (a builtin): let the call decide
        return None
    return None


class Environment:
    """Base class: set `name`, `tools` and `limits`, implement `reward`; override the rest when needed.

    The default episode: the system message introduces the tools (`tools_prompt`), the problem's `prompt` is the
    user message; every assistant turn's calls are answered by one `tool` message each; a turn without calls ends
    the episode."""

    name: str = "environment"
    description: str = ""
    tools: Sequence[Callable] = ()
    limits: Limits = Limits()
    instructions: str = ""  # a first line of the system message (the task), before the tools

    # ------------------------------------------------------------------ tools
    def tool_functions(self) -> dict[str, Callable]:
        out: dict[str, Callable] = {}
        for fn in self.tools:
            name = tool_name(fn)
            if name in out:
                raise ValueError(f"environment {self.name!r}: two tools are named {name!r}")
            out[name] = fn
        return out

    def tool_schemas(self) -> list[dict[str, Any]]:
        return [tool_schema(fn) for fn in self.tools]

    def tools_prompt(self) -> str:
        """The system message: `instructions`, the tools as JSON schemas (one per line) and the call format."""
        lines = [self.instructions] if self.instructions else []
        if self.tools:
            lines.append("Tools:")
            lines += [json.dumps(s.get("function", s), sort_keys=True) for s in self.tool_schemas()]
            lines.append('To call a tool, write <tool_call>{"name": "NAME", "arguments": {...}}</tool_call> and wait '
                         "for its result.")
        return "\n".join(lines)

    # ------------------------------------------------------------------ the episode
    def reset(self, problem: dict[str, Any]) -> list[dict[str, Any]]:
        """The first messages for a problem row (default: the tools prompt as the system message, then the row's
        `prompt` as the user message; a row whose `prompt` is a list of messages is used as it is, after it)."""
        prompt = problem.get("prompt")
        system = self.tools_prompt()
        head = [{"role": "system", "content": system}] if system else []
        if isinstance(prompt, list):
            return head + [dict(m) for m in prompt]
        if not isinstance(prompt, str) or not prompt:
            raise ValueError(f"environment {self.name!r}: a problem row needs a non-empty 'prompt' (got {prompt!r})")
        return head + [{"role": "user", "content": prompt}]

    def parse_calls(self, text: str, episode: Episode | None = None) -> list[ToolCall]:
        """The tool calls of an assistant turn's text (default: `parse_tool_calls`); `episode` is the episode so far
        (its problem, its earlier turns), for environments whose parsing depends on them."""
        return parse_tool_calls(text)

    def respond(self, episode: Episode, results: list[ToolResult]) -> list[dict[str, Any]]:
        """The messages appended after an assistant turn whose calls returned `results` (default: one `tool`
        message per result). Return [] to end the episode."""
        return [{"role": "tool", "content": r.content} for r in results]

    def turn_reward(self, episode: Episode, turn: Turn) -> float | None:
        """An optional reward for one turn (PPO can credit it to that turn); None: only the final reward."""
        return None

    def reward(self, episode: Episode) -> float:  # pragma: no cover - interface
        raise NotImplementedError(f"environment {self.name!r} must implement reward(episode)")

    def metrics(self, episode: Episode) -> dict[str, float]:
        """Extra per-episode numbers for the logs (default: none), asked after `reward(episode)`: names to finite
        numbers. The engine saves them in the rollout (`extras["episode"]["metrics"]`) and the trainers log their
        means as `env/<name>` (over the episodes that report each name)."""
        return {}


def episode_metrics(episodes: Sequence[dict[str, Any]]) -> dict[str, float]:
    """Means over episodes (each `Episode.to_dict()`, as saved in a rollout's `extras["episode"]`): turns, tool calls,
    valid calls, errors of each kind, tool seconds, sampled and environment tokens, and the share of episodes that
    called a tool and that ended with an answer; then each number of the environment's own `metrics` (the episode's
    "metrics"), as `env/<name>`, averaged over the episodes that report it (a name never shadows the ones above)."""
    n = max(1, len(episodes))
    calls = [c for e in episodes for t in e["turns"] for c in t["tool_calls"]]
    out = {
        "env/turns": sum(len(e["turns"]) for e in episodes) / n,
        "env/tool_calls": len(calls) / n,
        "env/valid_calls": sum(c["error"] is None for c in calls) / n,
        "env/called_a_tool": sum(any(t["tool_calls"] for t in e["turns"]) for e in episodes) / n,
        "env/answered": sum(e["finish"] == "answer" for e in episodes) / n,
        "env/tool_seconds": sum(c["seconds"] for c in calls) / n,
        "env/sampled_tokens": sum(e.get("sampled_tokens", 0) for e in episodes) / n,
        "env/env_tokens": sum(e.get("env_tokens", 0) for e in episodes) / n,
    }
    for kind in ERROR_KINDS:
        out[f"env/errors/{kind}"] = sum(c["error"] == kind for c in calls) / n
    reported: dict[str, list[float]] = {}  # the environment's own numbers (`Environment.metrics`)
    for e in episodes:
        for k, v in (e.get("metrics") or {}).items():
            reported.setdefault(k, []).append(float(v))
    for k, vs in sorted(reported.items()):
        out.setdefault(f"env/{k}", sum(vs) / len(vs))
    return out
