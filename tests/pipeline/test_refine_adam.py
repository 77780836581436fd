"""The refinement's Adam (:mod:`macsplat_cli.pipeline.refine_adam`): the bits of ``torch.optim.Adam``, without the
``torch._dynamo`` import that ``torch.optim`` costs on first use."""

from __future__ import annotations

import json
import subprocess
import sys

import torch

from macsplat_cli.pipeline.refine_adam import Adam


def _params(seed: int) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(4, 5, generator=g), torch.randn(7, generator=g), torch.randn(2, 3, 3, generator=g)]


def test_adam_steps_are_torch_optim_adams_bit_for_bit() -> None:
    """Two groups, a cosine-like rate set in place between steps, a parameter that has no gradient on some steps,
    gradients spanning eight orders of magnitude: every parameter equal to ``torch.optim.Adam``'s after each step."""
    ours, theirs = _params(0), _params(0)
    for p in ours + theirs:
        p.requires_grad_(True)
    opt_a = Adam([{"params": ours[:2], "lr": 3e-2}, {"params": ours[2:], "lr": 5e-3}])
    opt_b = torch.optim.Adam([{"params": theirs[:2], "lr": 3e-2}, {"params": theirs[2:], "lr": 5e-3}])
    g = torch.Generator().manual_seed(1)
    for step in range(12):
        for opt in (opt_a, opt_b):
            opt.zero_grad(set_to_none=True)
            for group in opt.param_groups:
                group["lr"] *= 0.9
        grads = [torch.randn(p.shape, generator=g) * 10.0 ** float(torch.randint(-6, 3, (), generator=g)) for p in ours]
        for i, gr in enumerate(grads):
            if i == 1 and step % 3 == 2:
                continue  # no gradient this step: Adam leaves it (and its moments) alone
            ours[i].grad, theirs[i].grad = gr.clone(), gr.clone()
        opt_a.step()
        opt_b.step()
        for a, b in zip(ours, theirs):
            assert torch.equal(a, b), step


def test_adam_imports_no_dynamo() -> None:
    """``torch.optim.Adam`` loads ``torch._dynamo`` (seconds) on its first use; ours does not."""
    code = (
        "import json, sys, torch\n"
        "from macsplat_cli.pipeline.refine_adam import Adam\n"
        "p = torch.zeros(3, requires_grad=True)\n"
        "opt = Adam([{'params': [p], 'lr': 0.1}]) if sys.argv[1] == 'ours' else torch.optim.Adam([p], lr=0.1)\n"
        "opt.zero_grad(set_to_none=True); p.sum().backward(); opt.step()\n"
        "print(json.dumps('torch._dynamo' in sys.modules))\n"
    )

    def dynamo_loaded(which: str) -> bool:
        run = subprocess.run([sys.executable, "-c", code, which], capture_output=True, text=True, check=True)
        return json.loads(run.stdout)

    assert dynamo_loaded("torch")  # what the check detects
    assert not dynamo_loaded("ours")
