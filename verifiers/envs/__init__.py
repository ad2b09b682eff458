"""Multi-turn environments with tools (torch-free): the protocol (`base`), the tool runner (`runner`), built-in
tools (`tools`) and environments (`calc`, `calc-words`, `lookup`), and the registry (`registry`: a name, an entry
point in group "posttrain.envs", or `path/to/file.py:Name`). The rollout engine that drives them is
`posttrain.rollout.multiturn`.
"""
from __future__ import annotations

from posttrain.verifiers.envs.base import (ERROR_KINDS, Environment, Episode, Limits, ToolCall, ToolResult, Turn,
                                           episode_metrics, format_tool_call, parse_tool_calls, tool_schema)
from posttrain.verifiers.envs.registry import get_env, list_envs
from posttrain.verifiers.envs.runner import Pending, ToolRunner

__all__ = ["ERROR_KINDS", "Environment", "Episode", "Limits", "Pending", "ToolCall", "ToolResult", "ToolRunner", "Turn",
           "episode_metrics", "format_tool_call", "get_env", "list_envs", "parse_tool_calls", "tool_schema"]
