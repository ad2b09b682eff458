"""final/ from a sharded model: FSDP2 keeps a shard of each weight in DTensor parameters, on which `save_pretrained`
fails; `loop.full_state_dict` gathers the whole weights and `models.save_model(..., state_dict=)` writes them.

Checked on the CPU: FSDP2 (`torch.distributed.fsdp.fully_shard`) runs over gloo in one process, in a subprocess so
the process group does not outlive the test. (accelerate does not apply FSDP on a machine without a GPU, so this
is the trainers' save path with the sharding done by torch directly; the same path ran under `accelerate launch
--config_file recipes/launch/fsdp.yaml` on an H200: RESULTS.md, "The GPU path".)
"""
import socket
import subprocess
import sys

import pytest

SCRIPT = r"""
import os, sys
import torch, torch.distributed as dist
src, port, out = sys.argv[1:4]
os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=port, RANK="0", WORLD_SIZE="1", LOCAL_RANK="0")
dist.init_process_group("gloo")
from torch.distributed.fsdp import fully_shard
from transformers import AutoModelForCausalLM, AutoTokenizer
from posttrain import loop, models
model = AutoModelForCausalLM.from_pretrained(src)
tok = AutoTokenizer.from_pretrained(src)
ref = {k: v.detach().clone() for k, v in model.state_dict().items()}
assert loop.full_state_dict(None, model) is None  # whole tensors: nothing to gather
for layer in model.model.layers:
    fully_shard(layer)
fully_shard(model)
assert type(next(model.parameters())).__name__ == "DTensor"
try:
    models.save_model(model, tok, out + "-plain")
    print("plain save_pretrained: ok")
except Exception as e:
    print(f"plain save_pretrained: {type(e).__name__}")
whole = loop.full_state_dict(None, model)
models.save_model(model, tok, out, state_dict=whole)
back = AutoModelForCausalLM.from_pretrained(out).state_dict()
missing = sorted(set(back) - set(ref))
diff = [k for k in back if k in ref and not torch.equal(ref[k], back[k])]
print(f"keys {len(back)} missing {missing} differ {diff[:3]}")
dist.destroy_process_group()
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_fsdp2_model_saves_its_whole_weights(tiny_lm, tmp_path):
    src = tiny_lm("tiny-summarize", max_length=128)
    proc = subprocess.run([sys.executable, "-c", SCRIPT, str(src), str(_free_port()), str(tmp_path / "final")],
                          capture_output=True, text=True, timeout=300, env={**__import__("os").environ,
                                                                               "CUDA_VISIBLE_DEVICES": ""})
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout
    assert "keys" in out and "missing []" in out and "differ []" in out, out
