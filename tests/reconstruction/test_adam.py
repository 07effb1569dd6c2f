"""`reconstruction.adam.Adam`: torch.optim.Adam's update bit for bit, its checkpoints, and no torch._dynamo import."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch

from reconstruction.adam import Adam


def _params(seed: int) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return [torch.randn(shape, generator=gen).requires_grad_(True) for shape in ((40, 3), (40, 9, 3), (7,), (3, 4))]


def _groups(params: list[torch.Tensor]) -> list[dict]:
    return [{"name": "a", "params": params[:2], "lr": 1e-2}, {"name": "b", "params": params[2:], "lr": 3e-3}]


def _train(opt, params: list[torch.Tensor], steps: range, gen: torch.Generator) -> None:
    """A run as training makes one: a schedule on one group's rate, a group frozen for a while, a state reset."""
    for step in steps:
        opt.param_groups[1]["lr"] = 3e-3 * 0.9**step
        opt.zero_grad(set_to_none=True)
        loss = sum((p.sin() * torch.randn(p.shape, generator=gen)).sum() for p in params[:2])
        if step >= 3:
            loss = loss + sum((p**2 * torch.rand(p.shape, generator=gen)).sum() for p in params[2:])
        loss.backward()
        opt.step()
        if step == 7:
            opt.state.pop(params[0], None)


@pytest.mark.parametrize("fused", [False, True])
def test_parameters_move_bit_for_bit_as_under_torch_adam(fused):
    ours, theirs = _params(0), _params(0)
    _train(Adam(_groups(ours), eps=1e-15, fused=fused), ours, range(12), torch.Generator().manual_seed(1))
    _train(torch.optim.Adam(_groups(theirs), eps=1e-15, fused=fused), theirs, range(12), torch.Generator().manual_seed(1))
    for a, b in zip(ours, theirs):
        assert torch.equal(a, b)


@pytest.mark.parametrize("first, then", [(torch.optim.Adam, Adam), (Adam, torch.optim.Adam)])
def test_a_checkpoint_of_either_resumes_in_the_other_exactly(first, then):
    straight, resumed = _params(0), _params(0)
    _train(Adam(_groups(straight), fused=True), straight, range(12), torch.Generator().manual_seed(2))
    gen = torch.Generator().manual_seed(2)
    half = first(_groups(resumed), fused=True)
    _train(half, resumed, range(5), gen)
    other = then(_groups(resumed), fused=True)
    other.load_state_dict(half.state_dict())
    _train(other, resumed, range(5, 12), gen)
    for a, b in zip(straight, resumed):
        assert torch.equal(a, b)


def test_a_checkpoint_for_other_groups_is_refused():
    opt = Adam(_groups(_params(0)))
    saved = Adam(_params(1)).state_dict()
    with pytest.raises(ValueError, match="other parameter groups"):
        opt.load_state_dict(saved)


def test_stepping_does_not_import_torch_dynamo():
    code = (
        "import sys, torch\n"
        "from reconstruction.adam import Adam\n"
        "p = torch.zeros(3, requires_grad=True)\n"
        "opt = Adam([p], lr=0.1, fused=True)\n"
        "p.sum().backward(); opt.step(); opt.zero_grad(); opt.load_state_dict(opt.state_dict())\n"
        "print('torch._dynamo' in sys.modules, float(p[0]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "False" and float(out[1]) == pytest.approx(-0.1)
