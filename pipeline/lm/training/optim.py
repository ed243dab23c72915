"""Optimizers the trainer can use besides Trainer's own AdamW (`TrainSettings.optimizer`).

``muon``: Muon (Jordan et al. 2024) for the hidden weight matrices of the decoder layers, AdamW for everything
else (embeddings, the tied head, norms), in one optimizer so that Trainer's scheduler, gradient clipping and
checkpoints treat it as any other. Muon's step is SGD momentum (Nesterov) whose update matrix is
orthogonalized by five Newton-Schulz iterations; its size is matched to AdamW's typical update RMS
(0.2 * sqrt(max(rows, columns)); Liu et al. 2025, "Muon is Scalable for LLM Training"), so the learning rate
and weight decay tuned for AdamW carry over unchanged. The AdamW part uses Trainer's defaults (betas 0.9 and
0.999, eps 1e-8), with weight decay on matrices only, as Trainer does.

The Newton-Schulz iterations run in fp32, or in bf16 as the reference implementation runs them (``ns_dtype``;
`TrainSettings.muon_bf16`): where training picks bf16, a CPU's bf16 matmuls measured 2.2x to 2.8x its fp32
ones. On more than one thread the matrices of one shape are orthogonalized together, as one batch of matmuls
(the same numbers, fewer and larger kernels; on one thread the batch measured slower, so each matrix goes alone
there).
"""

from __future__ import annotations

import math
from typing import Iterable

import torch
from torch import nn

from pipeline.lm.training.settings import OPTIMIZERS

# Newton-Schulz quintic coefficients (Jordan et al. 2024): five iterations take every singular value of the
# normalised update into about [0.7, 1.2], which is what Muon needs (not an exact orthogonalization).
_NS_COEFFICIENTS = (3.4445, -4.7750, 2.0315)


def orthogonalized(update: torch.Tensor, steps: int = 5, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The update matrix (or a batch of them, ``(..., rows, columns)``) with its singular values pushed towards 1
    (Newton-Schulz), computed in ``dtype``."""
    a, b, c = _NS_COEFFICIENTS
    x = update.to(dtype)
    tall = x.size(-2) > x.size(-1)
    if tall:
        x = x.mT
    x = x / (torch.linalg.vector_norm(x, dim=(-2, -1), keepdim=True) + 1e-7)
    for _ in range(steps):
        gram = x @ x.mT
        x = a * x + (b * gram + c * gram @ gram) @ x
    return x.mT if tall else x


class MuonAdamW(torch.optim.Optimizer):
    """Muon for the parameter groups with ``muon=True``, AdamW for the others (see the module docstring)."""

    def __init__(self, groups: Iterable[dict], lr: float, weight_decay: float = 0.0, momentum: float = 0.95,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8, ns_dtype: torch.dtype = torch.float32):
        defaults = dict(lr=lr, weight_decay=weight_decay, momentum=momentum, betas=betas, eps=eps, muon=False)
        super().__init__(list(groups), defaults)
        self.ns_dtype = ns_dtype
        for group in self.param_groups:
            if group["muon"]:
                bad = [tuple(p.shape) for p in group["params"] if p.ndim != 2]
                if bad:
                    raise ValueError(f"Muon takes 2-D weight matrices only; got shapes {bad}")

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            live = [p for p in group["params"] if p.grad is not None]
            if group["weight_decay"]:
                for p in live:
                    p.mul_(1 - group["lr"] * group["weight_decay"])
            if group["muon"]:
                self._muon(live, group)
            else:
                for p in live:
                    self._adamw(p, group)
        return loss

    def _muon(self, params: list[torch.Tensor], group: dict) -> None:
        updates = []
        for p in params:
            state = self.state[p]
            if "momentum_buffer" not in state:
                state["momentum_buffer"] = torch.zeros_like(p)
            buf, mu = state["momentum_buffer"], group["momentum"]
            buf.mul_(mu).add_(p.grad)
            updates.append(p.grad.add(buf, alpha=mu))  # Nesterov
        together = torch.get_num_threads() > 1
        for indices in _same_shapes(params) if together else ([i] for i in range(len(params))):
            if len(indices) == 1:  # a matrix alone: no stacking (measurably slower on one thread)
                batch = [orthogonalized(updates[indices[0]], dtype=self.ns_dtype)]
            else:
                batch = orthogonalized(torch.stack([updates[i] for i in indices]), dtype=self.ns_dtype)
            for i, update in zip(indices, batch):
                p = params[i]
                p.add_(update.to(p.dtype), alpha=-group["lr"] * 0.2 * math.sqrt(max(p.shape)))

    def _adamw(self, p: torch.Tensor, group: dict) -> None:
        state = self.state[p]
        if "step" not in state:
            state["step"] = 0
            state["exp_avg"] = torch.zeros_like(p)
            state["exp_avg_sq"] = torch.zeros_like(p)
        state["step"] += 1
        (beta1, beta2), t = group["betas"], state["step"]
        state["exp_avg"].lerp_(p.grad, 1 - beta1)
        state["exp_avg_sq"].mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
        denominator = (state["exp_avg_sq"] / (1 - beta2**t)).sqrt_().add_(group["eps"])
        p.addcdiv_(state["exp_avg"], denominator, value=-group["lr"] / (1 - beta1**t))


def _same_shapes(params: list[torch.Tensor]) -> list[list[int]]:
    """The indices of ``params`` grouped by shape, in the order each shape first appears."""
    groups: dict[tuple, list[int]] = {}
    for i, p in enumerate(params):
        groups.setdefault(tuple(p.shape), []).append(i)
    return list(groups.values())


def muon_groups(model: nn.Module) -> list[dict]:
    """The model's trainable parameters in three groups: the decoder layers' weight matrices (Muon), the
    other matrices (embeddings; AdamW with weight decay) and vectors (norms, biases; AdamW without decay).
    A tied head is the embedding itself, listed once."""
    layers = getattr(getattr(model, "base_model", model), "layers", None)
    if layers is None:
        raise ValueError(f"{type(model).__name__} has no decoder layers (base_model.layers) for Muon")
    inside = {id(p) for p in layers.parameters()}
    muon, matrices, vectors = [], [], []
    for p in model.parameters():  # unique parameters: a tied head is not listed twice
        if not p.requires_grad:
            continue
        if p.ndim == 2 and id(p) in inside:
            muon.append(p)
        else:
            (matrices if p.ndim >= 2 else vectors).append(p)
    groups = [dict(params=muon, muon=True), dict(params=matrices), dict(params=vectors, weight_decay=0.0)]
    return [g for g in groups if g["params"]]


def build_optimizer(name: str, model: nn.Module, lr: float, weight_decay: float,
                    ns_dtype: torch.dtype = torch.float32) -> torch.optim.Optimizer | None:
    """The optimizer ``name`` names, or None for ``adamw`` (Trainer builds its own). ``ns_dtype``: Muon's
    Newton-Schulz precision."""
    if name not in OPTIMIZERS:
        raise ValueError(f"optimizer={name!r} is not allowed; expected one of {', '.join(OPTIMIZERS)}")
    if name == "adamw":
        return None
    return MuonAdamW(muon_groups(model), lr=lr, weight_decay=weight_decay, ns_dtype=ns_dtype)
