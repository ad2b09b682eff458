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


def eos_pulled_copy(src, out, pull: float = 0.5):
    """A copy of the tiny chat model at `src` whose eos row of the output matrix points along the mean final hidden
    state of the calc environment's prompts, so that some turns (not all) end at eos within 12 tokens: the Turns
    reward then varies within a group. Returns `out`."""
    import torch

    from posttrain.chat import encode_prompts
    from posttrain.models import load_model, load_tokenizer, save_model
    from posttrain.verifiers.envs.calc import CalcEnv

    tok, model = load_tokenizer(src), load_model(src)
    ids = encode_prompts(tok, [CalcEnv().reset(p) for p in CalcEnv.problems(8)])
    with torch.no_grad():
        h = torch.cat([model.model(input_ids=torch.tensor([x])).last_hidden_state[0] for x in ids]).mean(0)
        model.lm_head.weight[tok.eos_token_id] = pull * h / h.norm()
    save_model(model, tok, out)
    return out
