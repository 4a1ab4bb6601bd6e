"""Run a snippet in a fresh Python under Triton's CPU interpreter (the CPU twin of the fused Triton kernels): Triton
reads ``TRITON_INTERPRET`` when a module's kernels are decorated, so each case needs its own process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# a snippet's LoRA-adapted network on the fused Triton MLP, adapters that move the law (needs torch, apply_lora)
NET_OF = '''
def net_of(cls, dtype, cfg=None):
    net = cls(cfg)
    apply_lora(net, 4, 4.0)
    for name, p in net.named_parameters():
        if name.endswith("lora_B"):
            torch.nn.init.normal_(p, std=0.05)  # adapters that move the law
    net = net.to(dtype)
    net.mlp_kernel = "triton_tf32"
    return net
'''


# a small neural material (net_of's networks, float ``dtype``) and 40 particles' scene for a snippet's rollouts (needs
# NET_OF, NeuralLawConfig, NeuralElasticity, NeuralPlasticity, Material and ``dtype``)
LAW_SCENE = '''
cfg = NeuralLawConfig(widths=(16, 16), stress_scale=2e3, alpha=1e-2)
material = Material(net_of(NeuralElasticity, dtype, cfg), net_of(NeuralPlasticity, dtype, cfg), 1000.0).to(dtype)
g = torch.Generator().manual_seed(1)
n = 40
x0 = (0.4 + 0.2 * torch.rand(n, 3, generator=g)).to(dtype)
v0 = (torch.tensor([0.3, -0.2, 0.1]) + 0.2 * torch.randn(n, 3, generator=g)).to(dtype)
vol = torch.full((n,), 2e-6, dtype=dtype)
'''


def run_interpreted(code: str, interpret: bool = True, cwd: Path = ROOT) -> str:
    """``code`` in a fresh Python in ``cwd`` (under Triton's interpreter unless ``interpret`` is False, which also
    clears an inherited ``TRITON_INTERPRET``); it must exit 0 and print "ok". Returns its stdout."""
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    if interpret:
        env["TRITON_INTERPRET"] = "1"
    out = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and "ok" in out.stdout, out.stdout + out.stderr
    return out.stdout
