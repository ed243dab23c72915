"""A batch cut into parts computed side by side by Python threads (pipeline/lm/training/parts.py)."""
import threading

import pytest
import torch
from transformers import TrainerCallback

from pipeline.lm.chat import WORD_LEVEL_FORMAT
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model, load_model
from grid_conversations import TINY, data, trained  # noqa: F401 - data: a fixture
from pipeline.lm.training.compile import compile_settings
from pipeline.lm.training.parts import PartThreads, split_rows
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.trainer import finetune
from pipeline.workflow.config import PYTHON_H, cxx_compiler



def batch(lengths, width, pad=0):
    ids = torch.full((len(lengths), width), pad)
    mask = torch.zeros((len(lengths), width), dtype=torch.long)
    for row, n in enumerate(lengths):
        ids[row, :n] = torch.arange(1, n + 1)
        mask[row, :n] = 1
    return {"input_ids": ids, "labels": ids.clone(), "attention_mask": mask,
            "position_ids": torch.arange(width).repeat(len(lengths), 1)}


def test_parts_are_consecutive_rows_cut_to_their_own_width():
    inputs = batch([3, 5, 9, 10, 17], width=24)
    parts = split_rows(inputs, 2, multiple=8)
    assert [p["input_ids"].shape for p in parts] == [(2, 8), (3, 24)]  # 5 -> 8; 17 -> 24 (the batch's own)
    assert all(p.keys() == inputs.keys() for p in parts)
    rows = torch.cat([torch.nn.functional.pad(p["input_ids"], (0, 24 - p["input_ids"].shape[1])) for p in parts])
    assert torch.equal(rows, inputs["input_ids"])  # nothing but padding was cut
    assert [p["input_ids"].shape[1] for p in split_rows(inputs, 2)] == [5, 17]
    assert [p["input_ids"].shape[0] for p in split_rows(batch([1], width=8), 2)] == [1]  # no empty part


def test_without_a_mask_parts_keep_the_batch_width():
    inputs = {k: v for k, v in batch([3, 5, 9], width=16).items() if k != "attention_mask"}
    assert [p["input_ids"].shape for p in split_rows(inputs, 2)] == [(2, 16), (1, 16)]


def test_part_threads_run_side_by_side_on_their_own_torch_threads_and_return_in_order():
    before = torch.get_num_threads()
    pool = PartThreads(2, intra_op=1)
    try:
        def call(value, barrier=None):
            def run():
                if barrier:
                    barrier.wait()  # passes only if the two calls run at the same time
                return value, torch.get_num_threads(), threading.current_thread().name
            return run

        first = pool.run([call("a"), call("b")])  # the first run goes one at a time (it may compile)
        assert first == [("a", 1, "batch-part-0"), ("b", 1, "batch-part-0")]
        both = threading.Barrier(2, timeout=10)
        results = pool.run([call("a", both), call("b", both)])
        assert [r[:2] for r in results] == [("a", 1), ("b", 1)]
        assert {r[2] for r in results} == {"batch-part-0", "batch-part-1"}
        assert torch.get_num_threads() == before  # the caller's threads keep their setting
    finally:
        pool.close()


def test_part_threads_run_their_calls_under_the_settings_given_which_torch_keeps_per_thread():
    assert not torch._dynamo.config.specialize_float  # torch's default, here and in any new thread
    pool = PartThreads(2, settings=compile_settings)
    try:
        def read():
            return torch._dynamo.config.specialize_float, torch.fx.experimental._config.use_duck_shape

        assert pool.run([read, read]) == [(True, False)] * 2
        assert pool.map([read, read]) == [(True, False)] * 2
        assert read() == (False, True)  # the caller's own settings are untouched
    finally:
        pool.close()
    with compile_settings():  # what compiled_blocks traces under, in the caller's thread
        assert (torch._dynamo.config.specialize_float, torch.fx.experimental._config.use_duck_shape) == (True, False)


def test_a_part_that_fails_raises_in_the_caller():
    pool = PartThreads(2)
    try:
        def boom():
            raise ValueError("part failed")
        pool.run([lambda: 1, lambda: 2])
        with pytest.raises(ValueError, match="part failed"):
            pool.run([lambda: 1, boom])
        assert pool.run([lambda: 3, lambda: 4]) == [3, 4]  # and the threads still serve
    finally:
        pool.close()


def test_map_runs_calls_side_by_side_in_order_and_raises_a_failure_after_all_finished():
    pool = PartThreads(2)
    try:
        both = threading.Barrier(2, timeout=10)
        ran = []

        def call(value):
            def run():
                both.wait()  # passes only if the two calls run at the same time
                ran.append(value)
                return value, torch.get_num_threads()
            return run

        assert pool.map([call("a"), call("b")]) == [("a", 1), ("b", 1)]

        def boom():
            raise ValueError("share failed")
        ran.clear()
        with pytest.raises(ValueError, match="share failed"):
            pool.map([boom, lambda: ran.append("other")])
        assert ran == ["other"]  # the other call was not abandoned
        assert pool.map([lambda: 3, lambda: 4]) == [3, 4]

        # `meanwhile` runs on the caller's thread while the calls run (all three meet at one barrier); its error is
        # raised once the calls have finished.
        three = threading.Barrier(3, timeout=10)
        caller = []
        meet = lambda: three.wait()  # noqa: E731
        shares = pool.map([meet, meet], meanwhile=lambda: caller.append((meet(), threading.current_thread())))
        assert sorted(shares + [caller[0][0]]) == [0, 1, 2] and caller[0][1] is threading.current_thread()

        def late_boom():
            raise RuntimeError("meanwhile failed")
        ran.clear()
        with pytest.raises(RuntimeError, match="meanwhile failed"):
            pool.map([lambda: ran.append("x"), lambda: ran.append("y")], meanwhile=late_boom)
        assert sorted(ran) == ["x", "y"]
        assert pool.map([lambda: 5, lambda: 6]) == [5, 6]
    finally:
        pool.close()


@pytest.mark.parametrize("stretch", [1.0, 2.0])
def test_parts_train_what_the_whole_batch_trains_and_the_same_each_run(data, tmp_path, stretch):
    settings = dict(max_steps=6, report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2,
                    per_device_batch_size=4, torch_threads=2, optimizer="muon", position_stretch=stretch)

    def run(name, **extra):
        return trained(data, tmp_path / name, **settings, **extra)

    whole, w = run("whole")
    parts, p = run("parts", batch_threads=2)
    again, q = run("again", batch_threads=2)
    assert parts.final_loss == pytest.approx(whole.final_loss, rel=1e-4)  # the same batches, loss and update
    assert all(torch.allclose(w[k], p[k], atol=1e-4) for k in w)
    assert again.final_loss == parts.final_loss and all(torch.equal(p[k], q[k]) for k in p)  # deterministic


def test_while_parts_train_the_caller_runs_on_one_thread_and_muons_step_on_the_part_threads(data, tmp_path):
    conversations, tokenizer = data
    seen = []

    class Watch(TrainerCallback):
        def on_step_end(self, args, state, control, optimizer=None, **kwargs):
            workers = getattr(optimizer, "optimizer", optimizer).side_by_side  # accelerate wraps the optimizer
            seen.append((torch.get_num_threads(), workers.parts if workers else None))

    before = torch.get_num_threads()
    model = build_scratch_model(tokenizer, ModelSettings(**TINY), seed=0)
    finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations,
             TrainSettings(max_steps=3, report_to=(), save_steps=100, per_device_batch_size=4, torch_threads=2,
                           optimizer="muon", batch_threads=2), tmp_path / "run", callbacks=[Watch()])
    assert seen == [(1, 2)] * 3
    assert torch.get_num_threads() == before


def test_batch_threads_beyond_two_are_refused_naming_the_value():
    with pytest.raises(ValueError, match="batch_threads=3.*from 1 to 2"):
        TrainSettings(batch_threads=3)


@pytest.mark.slow  # compiling the layer's C++ wrapper takes about a minute on 2 cores with an empty cache
@pytest.mark.skipif(cxx_compiler() is None or not PYTHON_H.is_file(), reason="torch.compile on a CPU needs a C++ "
                    "compiler and the Python headers")
def test_compiled_parts_train_what_eager_parts_train_and_compile_once(data, tmp_path):
    conversations, tokenizer = data
    settings = dict(max_steps=8, report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2,
                    per_device_batch_size=4, torch_threads=2, optimizer="muon", position_stretch=2.0,
                    batch_threads=2, pad_to_multiple_of=1, labelled_logits=True, labelled_last_layer=True)

    def run(name, compile_scope):  # eager attention, as the CPU default (sdpa's mask is None for a part unpadded)
        model = build_scratch_model(tokenizer, ModelSettings(**TINY, attn_implementation="eager"), seed=0)
        result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations,
                          TrainSettings(torch_compile=compile_scope, **settings), tmp_path / name)
        return result, load_model(result.model_dir).state_dict()

    eager, e = run("eager", "none")
    torch._dynamo.reset()
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    compiled, c = run("compiled", "regional")
    # One graph for every layer, the last one computed from the first trained position on, compiled once for every
    # part's widths and starts.
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs == 1
    assert compiled.final_loss == pytest.approx(eager.final_loss, rel=1e-3)
    assert all(torch.allclose(e[k], c[k], atol=1e-3) for k in e)


def test_a_job_on_fewer_threads_than_parts_keeps_its_batches_whole(data, tmp_path):
    conversations, tokenizer = data
    settings = dict(max_steps=4, report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2,
                    per_device_batch_size=4, torch_threads=1)

    def weights(name, **extra):
        model = build_scratch_model(tokenizer, ModelSettings(**TINY), seed=0)
        result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, TrainSettings(**settings, **extra),
                          tmp_path / name)
        return load_model(result.model_dir).state_dict()

    whole, parts = weights("whole"), weights("parts", batch_threads=2)
    assert all(torch.equal(whole[k], parts[k]) for k in whole)  # one thread: the parts would only cost time



def test_the_next_batch_fetched_during_muons_step_trains_the_same_batches_and_weights(data, tmp_path, monkeypatch):
    """With parts and Muon the trainer takes the next step's batch (and draws its stretched positions) while the
    part threads take Muon's step: the same batches in the same order, across an epoch's end, and the same weights
    bit for bit as fetching each batch when its step starts; nothing is fetched for a step after the last."""
    from pipeline.lm.training import trainer as trainer_module

    settings = dict(max_steps=13, report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2,
                    per_device_batch_size=4, torch_threads=2, optimizer="muon", position_stretch=2.0,
                    batch_threads=2)  # 10 batches an epoch: 13 steps meet the end of the first
    cls = trainer_module._Trainer

    def run(name, ahead):
        batches, taken, fetched = [], [], []
        get, fetch, split = cls.get_batch_samples, cls.fetch_ahead, trainer_module.split_rows

        def get_batch_samples(self, iterator, n, device):
            taken.append(self._ahead is not None and self._ahead[0] is iterator)
            return get(self, iterator, n, device)

        def fetch_ahead(self):
            if ahead:
                fetch(self)
                fetched.append(len(self._ahead[1][0]) if self._ahead else None)

        def split_rows(inputs, *args):  # the step's whole batch, its positions drawn
            batches.append({k: v.clone() for k, v in inputs.items()})
            return split(inputs, *args)

        with monkeypatch.context() as patch:
            patch.setattr(cls, "get_batch_samples", get_batch_samples)
            patch.setattr(cls, "fetch_ahead", fetch_ahead)
            patch.setattr(trainer_module, "split_rows", split_rows)
            result, weights = trained(data, tmp_path / name, **settings)
        return result, weights, batches, taken, fetched

    result, weights, batches, taken, fetched = run("ahead", True)
    plain, plain_weights, plain_batches, plain_taken, _ = run("plain", False)
    assert result.global_step == plain.global_step == 13
    assert taken == [False] + [True] * 9 + [False] + [True] * 2 and not any(plain_taken)  # a new epoch: fetched then
    assert fetched == [1] * 9 + [0] + [1] * 2 + [None]  # at the epoch's end nothing more; at the last step nothing
    assert len(batches) == len(plain_batches) == 13
    assert all(a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
               for a, b in zip(batches, plain_batches))
    assert "position_ids" in batches[0]
    assert all(torch.equal(weights[k], plain_weights[k]) for k in weights)
