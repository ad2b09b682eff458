"""Environments for the trainer tests (loaded as grpo.env=<this file>:Name): a random tiny model can play them."""
from posttrain.verifiers.envs import Environment, Limits, ToolCall


def add(a: int, b: int) -> str:
    """Add two integers.

    Args:
        a: the first number
        b: the second number
    """
    return str(a + b)


class Turns(Environment):
    """Every turn that ends at eos "calls" add (the turn's length + 1); the reward is 1 for an episode of at least two
    turns. A random model rarely samples eos within a turn's 12 tokens, so the reward varies within a group and
    GRPO can teach it to end its turns early."""

    name = "turns"
    tools = (add,)
    limits = Limits(max_turns=3, max_turn_tokens=12, max_total_tokens=96, tool_timeout_s=5.0)

    def parse_calls(self, text, episode=None):
        return [ToolCall("add", {"a": len(text), "b": 1}, text)]

    def reward(self, episode):
        return float(len(episode.turns) >= 2)
