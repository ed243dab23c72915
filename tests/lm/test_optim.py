import copy

import pytest
import torch

from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model
from pipeline.lm.tokenizer import build_word_tokenizer
from pipeline.lm.training.optim import MuonAdamW, build_optimizer, muon_groups, orthogonalized
from pipeline.lm.training.parts import PartThreads


@pytest.mark.parametrize("shape", [(16, 64), (64, 16), (32, 32)])
def test_newton_schulz_takes_every_singular_value_near_one(shape):
    update = torch.randn(*shape, generator=torch.Generator().manual_seed(0))
    out = orthogonalized(update)
    assert out.shape == update.shape
    values = torch.linalg.svdvals(out)
    assert values.min() > 0.5 and values.max() < 1.3
    # the same singular vectors: the update's direction is kept, only its spectrum flattened
    assert torch.nn.functional.cosine_similarity(out.flatten(), update.flatten(), dim=0) > 0.5


def test_newton_schulz_in_bf16_flattens_the_spectrum_too_and_returns_bf16():
    update = torch.randn(32, 128, generator=torch.Generator().manual_seed(0))
    out = orthogonalized(update, dtype=torch.bfloat16)
    assert out.dtype == torch.bfloat16
    values = torch.linalg.svdvals(out.float())
    assert values.min() > 0.5 and values.max() < 1.3
    assert (out.float() - orthogonalized(update)).abs().max() < 0.05  # bf16 rounding, not another result


def _textbook_newton_schulz(update: torch.Tensor) -> torch.Tensor:
    """Five quintic iterations as the reference implementation writes them, in fp64."""
    x = update.double()
    x = x.mT if x.size(-2) > x.size(-1) else x
    x = x / (x.norm(dim=(-2, -1), keepdim=True) + 1e-7)
    for _ in range(5):
        gram = x @ x.mT
        x = 3.4445 * x + (-4.7750 * gram + 2.0315 * gram @ gram) @ x
    return x.mT if update.size(-2) > update.size(-1) else x


@pytest.mark.parametrize("shape", [(32, 128), (128, 32), (4, 24, 96), (4, 32, 48), (32, 32)])
def test_newton_schulz_is_the_textbook_map_through_the_gram_matrix_or_not(shape):
    """Wide matrices (at least 2:1) iterate on their Gram matrix, the others directly: the same map either way."""
    generator = torch.Generator().manual_seed(0)
    rank = 4  # nearly low-rank, as a momentum update is: where the Gram matrix's rounding shows most
    low = (torch.randn(*shape[:-1], rank, generator=generator)
           @ torch.randn(*shape[:-2], rank, shape[-1], generator=generator))
    update = low + 0.01 * torch.randn(*shape, generator=generator)
    ours, textbook = orthogonalized(update), _textbook_newton_schulz(update)
    assert ours.dtype == torch.float32
    assert ((ours.double() - textbook).norm() / textbook.norm()) < 1e-3


def test_a_batch_of_matrices_is_orthogonalized_each_as_alone():
    batch = torch.randn(3, 48, 16, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(orthogonalized(batch), torch.stack([orthogonalized(m) for m in batch]))
    nested = batch.reshape(3, 1, 48, 16)  # more than one batch dimension: the same numbers
    torch.testing.assert_close(orthogonalized(nested), orthogonalized(batch).reshape(3, 1, 48, 16))


def test_no_iterations_leave_the_normalised_update():
    update = torch.randn(8, 32, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(orthogonalized(update, steps=0), update / (update.norm() + 1e-7))


@pytest.fixture(scope="module")
def model():
    tokenizer = build_word_tokenizer(["Grid is from (0, 0) to (1, 1). Goal: (1, 1)\nup down cut"], frame=2)
    settings = ModelSettings(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, max_length=64)
    return build_scratch_model(tokenizer, settings, seed=0)


def test_muon_takes_the_decoder_matrices_and_adamw_the_rest_each_parameter_once(model):
    groups = muon_groups(model)
    listed = [id(p) for g in groups for p in g["params"]]
    assert sorted(listed) == sorted(id(p) for p in model.parameters())  # every one, once (the head is tied)
    muon = {id(p) for p in groups[0]["params"]}
    assert groups[0]["muon"] and all(p.ndim == 2 for p in groups[0]["params"])
    for name, p in model.named_parameters():
        in_layer_matrix = ".layers." in f".{name}" and p.ndim == 2
        assert (id(p) in muon) == in_layer_matrix, name
    assert groups[-1]["weight_decay"] == 0.0 and all(p.ndim == 1 for p in groups[-1]["params"])


def test_muon_refuses_what_is_not_a_matrix():
    with pytest.raises(ValueError, match="2-D weight matrices only; got shapes \\[\\(3,\\)\\]"):
        MuonAdamW([dict(params=[torch.nn.Parameter(torch.ones(3))], muon=True)], lr=1e-3)


def test_build_optimizer_leaves_adamw_to_the_trainer_and_names_bad_choices(model):
    assert build_optimizer("adamw", model, 1e-3, 0.0) is None
    assert isinstance(build_optimizer("muon", model, 1e-3, 0.0), MuonAdamW)
    with pytest.raises(ValueError, match="optimizer='adam'.*adamw, muon"):
        build_optimizer("adam", model, 1e-3, 0.0)


def test_the_adamw_part_steps_as_torch_adamw():
    torch.manual_seed(0)
    a = torch.nn.Parameter(torch.randn(4, 3))
    b = torch.nn.Parameter(a.detach().clone())
    ours = MuonAdamW([dict(params=[a])], lr=1e-2, weight_decay=0.1)
    theirs = torch.optim.AdamW([b], lr=1e-2, weight_decay=0.1, betas=(0.9, 0.999), eps=1e-8)
    for step in range(5):
        grad = torch.randn(4, 3, generator=torch.Generator().manual_seed(step))
        for p, opt in ((a, ours), (b, theirs)):
            p.grad = grad.clone()
            opt.step()
    torch.testing.assert_close(a, b)


def test_the_muon_step_has_the_size_of_adamws_typical_update():
    """Matched RMS (0.2 * sqrt(max(rows, columns)) * lr): an orthogonal-ish update of RMS ~0.2 * lr."""
    p = torch.nn.Parameter(torch.zeros(32, 128))
    opt = MuonAdamW([dict(params=[p], muon=True)], lr=1e-2)
    p.grad = torch.randn(32, 128, generator=torch.Generator().manual_seed(0))
    opt.step()
    rms = p.detach().pow(2).mean().sqrt().item()
    assert 0.2 * 1e-2 * 0.6 < rms < 0.2 * 1e-2 * 1.3


@pytest.mark.parametrize("ns_dtype", [torch.float32, torch.bfloat16])
def test_muon_steps_the_same_on_one_thread_as_batched_on_two(model, ns_dtype):
    """On more than one thread the matrices of one shape are orthogonalized as one batch: the same numbers."""
    results = []
    threads = torch.get_num_threads()
    try:
        for n in (1, 2):
            torch.set_num_threads(n)
            copied = copy.deepcopy(model)
            opt = MuonAdamW(muon_groups(copied), lr=1e-2, ns_dtype=ns_dtype)
            for step in range(3):
                generator = torch.Generator().manual_seed(step)
                for p in copied.parameters():
                    p.grad = torch.randn(p.shape, generator=generator)
                opt.step()
            results.append([p.detach().clone() for p in copied.parameters()])
    finally:
        torch.set_num_threads(threads)
    moved = [not torch.equal(a, b) for a, b in zip(results[0], model.parameters())]
    assert all(moved)
    for one, two in zip(*results):
        torch.testing.assert_close(one, two)


@pytest.mark.parametrize("ns_dtype", [torch.float32, torch.bfloat16])
def test_muon_shared_out_among_part_threads_steps_as_batched_on_two_threads_bit_for_bit(model, ns_dtype):
    """With the trainer's part threads, each thread takes its share of every shape's matrices (batched as the
    whole stack would be on two threads) while the caller runs on one thread: the same numbers, bit for bit. Odd
    stacks too (three matrices of a shape, one of them tall: a share of one)."""
    odd = [torch.randn(shape, generator=torch.Generator().manual_seed(i))
           for i, shape in enumerate([(32, 32)] * 3 + [(64, 16), (16, 64), (16, 64)])]
    results = []
    threads = torch.get_num_threads()
    workers = PartThreads(2, intra_op=1)
    try:
        for shared in (False, True):
            torch.set_num_threads(1 if shared else 2)
            copied = copy.deepcopy(model)
            extra = [torch.nn.Parameter(m.clone()) for m in odd]
            groups = muon_groups(copied) + [dict(params=extra, muon=True)]
            opt = MuonAdamW(groups, lr=1e-2, weight_decay=0.1, ns_dtype=ns_dtype)
            opt.side_by_side = workers if shared else None
            for step in range(3):
                generator = torch.Generator().manual_seed(step)
                for p in [*copied.parameters(), *extra]:
                    p.grad = torch.randn(p.shape, generator=generator)
                opt.step()
            results.append([p.detach().clone() for p in [*copied.parameters(), *extra]])
    finally:
        workers.close()
        torch.set_num_threads(threads)
    assert all(not torch.equal(a, b) for a, b in zip(results[0], [*model.parameters(), *odd]))
    assert all(torch.equal(a, b) for a, b in zip(*results))


def test_muons_stacked_momentum_is_saved_per_parameter_and_a_reload_steps_as_if_never_stopped(model):
    """The momentum lives in one stack per shape; its slices are the state entries a checkpoint saves, and a loaded
    state (separate tensors) is stacked again: the steps after a reload are those of an uninterrupted run, bit for bit."""
    def grads(m, step):
        generator = torch.Generator().manual_seed(step)
        for p in m.parameters():
            p.grad = torch.randn(p.shape, generator=generator)

    straight, resumed = copy.deepcopy(model), copy.deepcopy(model)
    opt = MuonAdamW(muon_groups(straight), lr=1e-2)
    for step in range(4):
        grads(straight, step)
        opt.step()
    first = MuonAdamW(muon_groups(resumed), lr=1e-2)
    for step in range(2):
        grads(resumed, step)
        first.step()
    saved = copy.deepcopy(first.state_dict())
    for p in muon_groups(resumed)[0]["params"]:
        assert first.state[p]["momentum_buffer"].shape == p.shape
    again = MuonAdamW(muon_groups(resumed), lr=1e-2)
    again.load_state_dict(saved)
    for step in range(2, 4):
        grads(resumed, step)
        again.step()
    for a, b in zip(straight.parameters(), resumed.parameters()):
        assert torch.equal(a, b)
