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
ones. Each iteration's sums are fused into its matmuls (``addmm``: alpha * A @ B + beta * C in one kernel); in
fp32 a matrix at least twice as wide as tall runs its iterations on its Gram matrix (`_through_gram`). The
matrices of one shape, a tall one counted as its transpose, are stacked once a step: their gradients in one
copy, their momentum kept as one stack (each parameter's state entry a slice of it), so the momentum's
element-wise work is a few kernels over the stack, with the same numbers. On more than one thread they are
orthogonalized together, as one batch of matmuls (the same numbers, fewer and larger kernels; on one thread the
batch measured slower, so each matrix goes alone there). With the trainer's part threads (`side_by_side`;
`TrainSettings.batch_threads`) each thread takes its share of every shape's matrices, batched as on two threads:
the same numbers, and the caller's own thread free to run on one intra-op thread: it steps the AdamW groups
meanwhile, then makes the calls in ``meanwhile`` (the trainer's: the composed rows written anew, the next batch
fetched), work that would otherwise wait between two steps with both worker threads idle. The rest of the element-wise
work (weight decay, the AdamW moments) runs as torch's multi-tensor (``_foreach``) kernels: one call for a list of
tensors.
"""

from __future__ import annotations

import functools
import math
from typing import Callable, Iterable, Protocol, Sequence

import torch
from torch import nn

from pipeline.lm.training.settings import OPTIMIZERS

# Newton-Schulz quintic coefficients (Jordan et al. 2024): five iterations take every singular value of the
# normalised update into about [0.7, 1.2], which is what Muon needs (not an exact orthogonalization).
_NS_COEFFICIENTS = (3.4445, -4.7750, 2.0315)


def orthogonalized(update: torch.Tensor, steps: int = 5, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """The update matrix (or a batch of them, ``(..., rows, columns)``) with its singular values pushed towards 1
    (Newton-Schulz), computed in ``dtype``. A matrix at least twice as wide as tall (or tall as wide) goes through
    its Gram matrix (`_through_gram`) in fp32 and wider types."""
    if update.ndim > 3:  # one batch dimension for the batched matmuls
        return orthogonalized(update.flatten(0, -3), steps, dtype).unflatten(0, update.shape[:-2])
    a, b, c = _NS_COEFFICIENTS
    x = update.to(dtype)
    tall = x.size(-2) > x.size(-1)
    if tall:
        x = x.mT
    x = x / (torch.linalg.vector_norm(x, dim=(-2, -1), keepdim=True) + 1e-7)
    addmm = torch.baddbmm if x.ndim == 3 else torch.addmm
    if steps > 0 and x.size(-1) >= 2 * x.size(-2) and torch.finfo(dtype).bits >= 32:
        x = _through_gram(x, steps, addmm)
    else:
        for _ in range(steps):
            gram = x @ x.mT
            # x <- a x + (b gram + c gram @ gram) @ x, each sum fused into its matmul
            x = addmm(x, addmm(gram, gram, gram, beta=b, alpha=c), x, beta=a)
    return x.mT if tall else x


def _through_gram(x: torch.Tensor, steps: int, addmm) -> torch.Tensor:
    """The Newton-Schulz iterations of a wide ``x`` (m rows, n >= 2m columns) carried out on its m x m Gram matrix
    G = x x^T. Each iteration multiplies x on the left by P = a I + b G + c G^2, so the result is Q x with Q the
    product of the P's, and the next G is P G P = P^2 G (P is a polynomial in G: they commute). The same map in
    2m^2 n + 17m^3 multiply-adds against 10m^2 n + 5m^3 directly: 1.8x fewer at n = 4m (the MLP's matrices of
    the CPU default); below n = 1.5m the direct iterations are cheaper, hence the 2:1 threshold. The rounding
    differs: against fp64, 1e-6 relative on random matrices and 1e-4 to 4e-4 on nearly low-rank ones (as momentum
    is) in fp32, against 1e-6 and 2e-5 directly; bf16 would lose far more (the Gram matrix squares the condition
    number), so bf16 iterations go directly."""
    a, b, c = _NS_COEFFICIENTS
    gram = x @ x.mT
    scaled_eye = torch.eye(gram.size(-1), dtype=gram.dtype, device=gram.device).mul_(a).expand_as(gram)
    product = None
    for i in range(steps):
        p = addmm(torch.add(scaled_eye, gram, alpha=b), gram, gram, alpha=c)  # a I + b G + c G^2
        product = p if product is None else p @ product
        if i < steps - 1:
            gram = p @ (p @ gram)
    return product @ x


class SideBySide(Protocol):
    """Worker threads, one intra-op thread each, that run calls side by side (`pipeline.lm.training.parts`)."""

    parts: int

    def map(self, calls: Sequence[Callable], meanwhile: Callable[[], object] | None = None) -> list: ...


def _nothing() -> None:
    pass


class MuonAdamW(torch.optim.Optimizer):
    """Muon for the parameter groups with ``muon=True``, AdamW for the others (see the module docstring)."""

    def __init__(self, groups: Iterable[dict], lr: float, weight_decay: float = 0.0, momentum: float = 0.95,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8, ns_dtype: torch.dtype = torch.float32):
        defaults = dict(lr=lr, weight_decay=weight_decay, momentum=momentum, betas=betas, eps=eps, muon=False)
        super().__init__(list(groups), defaults)
        self.ns_dtype = ns_dtype
        self.side_by_side: SideBySide | None = None  # worker threads for Muon's step (the trainer's batch parts)
        # Calls the caller's thread makes after the AdamW groups' step, while the worker threads take Muon's (the
        # trainer's: the composed rows written anew, the next batch fetched); without workers, after the step.
        self.meanwhile: list[Callable[[], object]] = []
        self._stacks: dict[tuple, tuple[torch.Tensor, list[torch.Tensor]]] = {}
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
        groups = [(group, [p for p in group["params"] if p.grad is not None]) for group in self.param_groups]
        groups = [(group, live) for group, live in groups if live]
        adamw = [(group, live) for group, live in groups if not group["muon"]]

        def adamw_steps() -> None:
            for group, live in adamw:
                if group["weight_decay"]:
                    torch._foreach_mul_(live, 1 - group["lr"] * group["weight_decay"])
                self._adamw(live, group)
            for call in self.meanwhile:
                call()

        pending = adamw_steps
        for group, live in groups:
            if group["muon"]:
                # With worker threads the AdamW groups step on this thread meanwhile (their parameters are others).
                pending = self._muon(live, group, meanwhile=pending)
        pending()
        return loss

    def _muon(self, params: list[torch.Tensor], group: dict, meanwhile: Callable[[], None] = _nothing):
        """Muon's step for ``params``; returns what of ``meanwhile`` is left to run. With worker threads
        (`side_by_side`) ``meanwhile`` runs on this thread while they work (nothing is left); without, none of it
        has run."""
        stacks = []  # (parameters of one shape, which are tall, their momentum stack)
        for indices in _same_shapes(params):
            ps = [params[i] for i in indices]
            tall = [p.size(0) > p.size(1) for p in ps]
            stacks.append((ps, tall, self._stacked(ps, tall, "momentum_buffer")))
        workers = self.side_by_side
        if workers is None or workers.parts < 2 or len(params) < 2:
            together = torch.get_num_threads() > 1
            for ps, tall, buffers in stacks:
                self._muon_rows(ps, tall, buffers, group, batched=together and len(ps) > 1)
            return meanwhile
        # Each worker thread takes its share of every stack's rows, batched as the whole stack would be on two
        # threads: the same numbers (a batched matmul computes each matrix alone), computed side by side.
        workers.map([functools.partial(self._muon_share, stacks, group, i, workers.parts)
                     for i in range(workers.parts)], meanwhile=meanwhile)
        return _nothing

    @torch.no_grad()  # grad mode is per thread
    def _muon_share(self, stacks: list, group: dict, share: int, shares: int) -> None:
        for ps, tall, buffers in stacks:
            start, stop = (round(i * len(ps) / shares) for i in (share, share + 1))
            if stop > start:
                self._muon_rows(ps[start:stop], tall[start:stop], buffers[start:stop], group, batched=len(ps) > 1)

    def _muon_rows(self, ps: list[torch.Tensor], tall: list[bool], buffers: torch.Tensor, group: dict,
                   batched: bool) -> None:
        """Muon's step for same-shaped ``ps`` whose momentum is the stack ``buffers``; ``batched``: their updates
        orthogonalized as one batch of matmuls (tall ones as their transposes), else each as it lies."""
        if group["weight_decay"]:
            torch._foreach_mul_(ps, 1 - group["lr"] * group["weight_decay"])
        mu = group["momentum"]
        # The gradients of one shape in one stacked copy (tall ones as their transposes) and the momentum kept as
        # one stack: the element-wise work is a few kernels over the stack instead of a few for each matrix.
        updates = torch.stack([p.grad.mT if t else p.grad for p, t in zip(ps, tall)])
        buffers.mul_(mu).add_(updates)
        updates.add_(buffers, alpha=mu)  # Nesterov: the gradient plus mu times the new momentum
        if batched:
            batch = list(orthogonalized(updates, dtype=self.ns_dtype))
        else:  # each matrix alone, as it lies (the batch measured slower on one thread)
            batch = [orthogonalized(u.mT.contiguous(), dtype=self.ns_dtype).mT if t else
                     orthogonalized(u, dtype=self.ns_dtype) for u, t in zip(updates, tall)]
        size = -group["lr"] * 0.2 * math.sqrt(max(ps[0].shape))
        torch._foreach_add_(ps, [(u.mT if t else u).to(p.dtype) for p, u, t in zip(ps, batch, tall)], alpha=size)

    def _stacked(self, ps: list[torch.Tensor], tall: list[bool], key: str) -> torch.Tensor:
        """The state ``key`` of same-shaped ``ps`` (tall ones transposed) as one stacked tensor whose slices are the
        per-parameter state entries (what `state_dict` saves and `load_state_dict` restores). Built from those
        entries (zeros where there is none) whenever they are not its slices: at the first step, and after a load."""
        stack, views = self._stacks.get((key, *map(id, ps)), (None, ()))
        if stack is None or any(self.state[p].get(key) is not v for p, v in zip(ps, views)):
            entries = [torch.zeros_like(p) if self.state[p].get(key) is None else self.state[p][key] for p in ps]
            stack = torch.stack([e.mT if t else e for e, t in zip(entries, tall)])
            views = [v.mT if t else v for v, t in zip(stack, tall)]
            for p, v in zip(ps, views):
                self.state[p][key] = v
            self._stacks[(key, *map(id, ps))] = (stack, views)
        return stack

    def _adamw(self, params: list[torch.Tensor], group: dict) -> None:
        for p in params:
            if "step" not in self.state[p]:
                self.state[p].update(step=0, exp_avg=torch.zeros_like(p), exp_avg_sq=torch.zeros_like(p))
            self.state[p]["step"] += 1
        beta1, beta2 = group["betas"]
        by_step: dict[int, list[torch.Tensor]] = {}  # parameters stepped as often share one bias correction
        for p in params:
            by_step.setdefault(self.state[p]["step"], []).append(p)
        for t, ps in by_step.items():
            grads = [p.grad for p in ps]
            exp_avg = [self.state[p]["exp_avg"] for p in ps]
            exp_avg_sq = [self.state[p]["exp_avg_sq"] for p in ps]
            torch._foreach_lerp_(exp_avg, grads, 1 - beta1)
            torch._foreach_mul_(exp_avg_sq, beta2)
            torch._foreach_addcmul_(exp_avg_sq, grads, grads, value=1 - beta2)
            denominator = torch._foreach_div(exp_avg_sq, 1 - beta2**t)
            torch._foreach_sqrt_(denominator)
            torch._foreach_add_(denominator, group["eps"])
            torch._foreach_addcdiv_(ps, exp_avg, denominator, value=-group["lr"] / (1 - beta1**t))


def _same_shapes(params: list[torch.Tensor]) -> list[list[int]]:
    """The indices of ``params`` grouped by shape, a tall matrix counted as its transpose (rows and columns
    sorted), in the order each shape first appears."""
    groups: dict[tuple, list[int]] = {}
    for i, p in enumerate(params):
        groups.setdefault(tuple(sorted(p.shape)), []).append(i)
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
