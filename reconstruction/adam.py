"""Adam over parameter groups: `torch.optim.Adam`'s update, without its first-call import of torch._dynamo.

torch's optimizer classes wrap their methods in `torch._disable_dynamo`, whose first call imports torch._dynamo,
once per process, paid by every one-shot `cadsplat reconstruct` before its first step
(benchmarks/results/rig_scenes.md). The update here is torch's own functional `torch.optim.adam.adam` (the same
kernels, on the same per-parameter state), which imports nothing outside `torch.compile`; parameters move bit for bit as
under `torch.optim.Adam` with the same arguments. `state_dict` has torch's layout, so checkpoints written by
either load into the other.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor
from torch.optim.adam import adam

_HYPERPARAMETERS = ("lr", "betas", "eps")
# torch.optim.Adam's other group settings, as this class fixes them: written into `state_dict` so that torch's
# class, which takes a saved group's settings whole, can resume from it.
_TORCH_GROUP = {
    "weight_decay": 0.0,
    "amsgrad": False,
    "maximize": False,
    "foreach": None,
    "capturable": False,
    "differentiable": False,
    "decoupled_weight_decay": False,
}


class Adam:
    """Adam (no weight decay, no amsgrad) over `params`: tensors, or groups {"params": [...], "lr": ..., ...}.

    Each group keeps its own `lr`, `betas` and `eps` (read at every step, so a schedule may change them);
    parameters without a gradient are skipped, and their state is created at their first step. `fused` runs
    torch's fused CPU kernel, one pass over all of a group's parameters (`torch.optim.Adam(fused=True)`).
    """

    def __init__(
        self,
        params: Iterable[Tensor] | Iterable[dict],
        lr: float = 1e-3,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
        fused: bool = False,
    ) -> None:
        groups = list(params)
        if groups and not isinstance(groups[0], dict):
            groups = [{"params": groups}]
        defaults = {"lr": lr, "betas": betas, "eps": eps}
        self.param_groups: list[dict[str, Any]] = [{**defaults, **g, "params": list(g["params"])} for g in groups]
        self.fused = fused
        self.state: dict[Tensor, dict[str, Tensor]] = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if set_to_none:
                    p.grad = None
                elif p.grad is not None:
                    p.grad.zero_()

    def _state_of(self, p: Tensor) -> dict[str, Tensor]:
        if p not in self.state:
            # As torch.optim.Adam: a float32 scalar step, moments shaped and laid out like the parameter.
            self.state[p] = {
                "step": torch.zeros((), dtype=torch.float32),
                "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format),
            }
        return self.state[p]

    @torch.no_grad()
    def step(self) -> None:
        for group in self.param_groups:
            params = [p for p in group["params"] if p.grad is not None]
            if not params:
                continue
            states = [self._state_of(p) for p in params]
            beta1, beta2 = group["betas"]
            adam(
                params,
                [p.grad for p in params],
                [s["exp_avg"] for s in states],
                [s["exp_avg_sq"] for s in states],
                [],
                [s["step"] for s in states],
                foreach=False,
                fused=self.fused,
                grad_scale=None,
                found_inf=None,
                has_complex=False,
                decoupled_weight_decay=False,
                amsgrad=False,
                beta1=beta1,
                beta2=beta2,
                lr=group["lr"],
                weight_decay=0.0,
                eps=group["eps"],
                maximize=False,
                capturable=False,
                differentiable=False,
            )

    def state_dict(self) -> dict[str, Any]:
        """torch's layout: parameters numbered in group order; state and groups refer to them by number."""
        index: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            ids = [index.setdefault(id(p), len(index)) for p in group["params"]]
            groups.append({**_TORCH_GROUP, "fused": self.fused, **{k: v for k, v in group.items() if k != "params"}, "params": ids})
        state = {index[id(p)]: dict(s) for p, s in self.state.items() if id(p) in index}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, saved: dict[str, Any]) -> None:
        """State and hyperparameters from `state_dict` (this class's or torch.optim.Adam's) of the same groups."""
        if len(saved["param_groups"]) != len(self.param_groups) or any(
            len(s["params"]) != len(g["params"]) for s, g in zip(saved["param_groups"], self.param_groups)
        ):
            raise ValueError("the saved optimizer state is for other parameter groups")
        self.state = {}
        for saved_group, group in zip(saved["param_groups"], self.param_groups):
            group.update({k: saved_group[k] for k in _HYPERPARAMETERS if k in saved_group})
            for i, p in zip(saved_group["params"], group["params"]):
                if i in saved["state"]:
                    s = saved["state"][i]
                    self.state[p] = {
                        "step": s["step"].to(torch.float32).reshape(()).clone(),
                        "exp_avg": s["exp_avg"].to(p).clone(),
                        "exp_avg_sq": s["exp_avg_sq"].to(p).clone(),
                    }
