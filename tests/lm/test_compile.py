"""The decoder layers compiled as one graph (`train.torch_compile=stacked`), and the process that compiles them
beside a job's data-build (`compile_beside`)."""
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torch._inductor.runtime.cache_dir_utils import cache_dir, temporary_cache_dir
from transformers import TrainerCallback

from grid_conversations import TINY, data  # noqa: F401 - data: a fixture
from pipeline.lm.chat import WORD_LEVEL_FORMAT
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model, load_model
from pipeline.lm.tokenizer import build_word_tokenizer
from pipeline.lm.training import compile as compile_module
from pipeline.lm.training import beside
from pipeline.lm.training.precompile import made_up_conversations
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.trainer import finetune
from pipeline.workflow.config import PYTHON_H, cxx_compiler

QUIET = dict(report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2, per_device_batch_size=4)
needs_compiler = pytest.mark.skipif(cxx_compiler() is None or not PYTHON_H.is_file(),
                                    reason="torch.compile on a CPU needs a C++ compiler and the Python headers")


@pytest.fixture
def no_process_yet(monkeypatch):
    """`compile_beside` and `warm_compiler` as in a fresh process, on a CPU."""
    monkeypatch.setattr(compile_module, "_beside", None)
    monkeypatch.setattr(beside, "_early", None)
    monkeypatch.setattr(compile_module, "_warming", None)
    monkeypatch.setattr(compile_module, "_PEAKS", {})
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def _fxgraph_entries() -> set[str]:
    folder = Path(cache_dir()) / "fxgraph"
    return {str(path.relative_to(folder)) for path in folder.rglob("*") if path.is_file()}


@pytest.mark.slow  # a 2-layer stack and a layer compiled, about 60 s on 2 cores with an empty cache
@needs_compiler
def test_stacked_layers_train_the_layers_own_numbers_bit_for_bit_and_save_plain_weights(data, tmp_path):
    conversations, tokenizer = data
    steps = 10  # 40 conversations in batches of 4: batches of several widths
    settings = dict(max_steps=steps, pad_to_multiple_of=1, torch_threads=1, bf16=True, **QUIET)
    # The CPU default's widths: in bf16 a stack fused across its layers (no boundary) rounded otherwise at these.
    shape = ModelSettings(**{**TINY, "hidden_size": 128, "intermediate_size": 512})
    regional = finetune(build_scratch_model(tokenizer, shape, seed=0), tokenizer, WORD_LEVEL_FORMAT,
                        conversations, TrainSettings(torch_compile="regional", **settings), tmp_path / "regional")
    model = build_scratch_model(tokenizer, shape, seed=0)
    layers = model.model.layers
    torch._dynamo.reset()
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    seen = []

    class Stacked(TrainerCallback):
        def on_step_end(self, args, state, control, **kwargs):
            whole = layers[:len(layers)]
            seen.append((len(whole), callable(whole[0]) and not isinstance(whole[0], torch.nn.Module),
                         type(layers[0]).__name__, len(layers[:1]), [name for name, _ in layers.named_children()]))

    stacked = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations,
                       TrainSettings(torch_compile="stacked", **settings), tmp_path / "stacked", callbacks=[Stacked()])
    # While training the model's loop over all its layers meets one compiled call; a layer or a part of the list is
    # still the module(s), under the same names ...
    assert seen == [(1, True, "LlamaDecoderLayer", 1, ["0", "1"])] * steps
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs == 1  # ... one graph, for every width
    assert type(layers) is torch.nn.ModuleList and "_in_turn" not in vars(layers)  # ... and a plain list after
    # No kernel spans two layers (a boundary inductor cannot see into), so the numbers are the layers' own.
    assert stacked.final_loss == regional.final_loss and stacked.mean_loss == regional.mean_loss
    a, b = load_model(regional.model_dir).state_dict(), load_model(stacked.model_dir).state_dict()
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_the_layer_boundary_is_a_copy_forward_and_backward():
    x = torch.randn(3, 5, 4, requires_grad=True)
    y = compile_module.layer_boundary(x)
    assert torch.equal(y, x) and y.data_ptr() != x.data_ptr()
    (y * torch.arange(4.0)).sum().backward()
    assert torch.equal(x.grad, torch.arange(4.0).expand(3, 5, 4))


def test_the_made_up_conversations_are_made_of_words_the_tokenizer_has():
    conversations = made_up_conversations(6, "composed")
    tokenizer = build_word_tokenizer((t["value"] for c in conversations for t in c), frame=6, numbers="digits",
                                     newlines="composed")
    ids = [tokenizer.encode(t["value"], add_special_tokens=False) for c in conversations for t in c]
    assert tokenizer.unk_token_id is None or all(tokenizer.unk_token_id not in row for row in ids)
    lengths = [len(tokenizer.encode(c[1]["value"], add_special_tokens=False)) for c in conversations]
    assert len(set(lengths)) == len(conversations) and min(lengths) > 8  # a batch of several widths, none of 1


@pytest.mark.parametrize("change", [dict(model=dict(kind="hf", path="somewhere")), dict(threads=1),
                                    dict(train=dict(torch_compile="none")), dict(cuda=True)])
def test_no_process_beside_where_the_job_would_not_compile_its_layers_here(change, no_process_yet, monkeypatch):
    monkeypatch.setattr(beside.subprocess, "Popen", lambda *a, **k: pytest.fail("started a process"))
    monkeypatch.setattr(compile_module, "warm_compiler", lambda: warmed.append(True))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: change.get("cuda", False))
    monkeypatch.setattr(torch, "get_num_threads", lambda: change.get("threads", 2))
    warmed = []
    model = ModelSettings(**{**TINY, **change.get("model", {})})
    train = TrainSettings(**{"torch_compile": "stacked", **change.get("train", {})})
    assert not compile_module.compile_beside(model, train, 6)
    # The checks of the C++ compiler still start early where the job compiles its layers on this CPU.
    assert warmed == ([True] if "threads" in change or "model" in change else [])


def test_the_process_beside_takes_the_jobs_settings_and_a_failure_costs_only_its_compile(
        no_process_yet, monkeypatch, caplog, tmp_path):
    started, real, received = [], subprocess.Popen, tmp_path / "received.json"

    def popen(command, **kwargs):  # a process that keeps what it is sent, then fails
        started.append(command)
        keep = f"import sys; open({str(received)!r}, 'w').write(sys.stdin.read()); raise SystemExit(3)"
        return real([sys.executable, "-c", keep], **kwargs)

    monkeypatch.setattr(beside.subprocess, "Popen", popen)
    monkeypatch.setattr(compile_module, "matmul_peak", lambda dtype, **_: {torch.float32: 300.0}.get(dtype, 100.0))
    monkeypatch.setattr(compile_module, "cpu_has_bf16", lambda: True)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    train = TrainSettings(torch_compile="stacked", bf16=True, bf16_when_faster=True, batch_threads=2)
    assert compile_module.compile_beside(ModelSettings(**TINY), train, 6)
    assert not compile_module.compile_beside(ModelSettings(**TINY), train, 6)  # once a process
    (command,) = started
    assert command[1:3] == ["-m", "pipeline.lm.training.precompile"]
    with caplog.at_level("WARNING", logger="pipeline.lm.training.compile"):
        compile_module._warmed()  # what compiled_blocks waits for
    assert "exit status 3" in caplog.text and "compiling it here" in caplog.text
    output = compile_module._beside[1]
    assert str(output) in caplog.text and output.is_file()  # its output kept, to be read
    shutil.rmtree(output.parent)
    sent = json.loads(received.read_text())
    # bf16 decided here, measured once: bf16 slower than fp32 on this "CPU", so neither process trains in bf16
    assert (sent["bf16"], sent["threads"], sent["frame"]) == (False, 2, 6)
    assert TrainSettings.from_dict(sent["train"]) == train and ModelSettings(**sent["model"]) == ModelSettings(**TINY)
    assert compile_module._PEAKS == {2: (300.0, 100.0)}


def test_the_process_started_with_the_command_line_imports_then_takes_the_settings_or_ends(monkeypatch):
    assert beside._early is None
    beside.start_early(["--help"])
    assert beside._early is None  # no job: no process
    beside.start_early(["tracking.root=x"])
    process, output = beside._early
    try:
        assert beside.take() == (process, output) and beside.take() is None  # handed on once
        beside.send(process, None)  # a job that compiles nothing here ends it
        assert process.wait(timeout=120) == 0
        assert not output.parent.exists()
    finally:
        monkeypatch.setattr(beside, "_early", None)
        if process.poll() is None:
            process.kill()


def test_a_job_that_compiles_nothing_here_ends_the_early_process(no_process_yet, monkeypatch):
    ended = []
    monkeypatch.setattr(beside, "take", lambda: (FakeProcess(), Path("nowhere")))
    monkeypatch.setattr(beside, "send", lambda process, settings: ended.append(settings))
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    assert not compile_module.compile_beside(ModelSettings(**TINY), TrainSettings(torch_compile="regional"), 6)
    assert ended == [None]


class FakeProcess:
    def poll(self):
        return None


def test_a_reused_training_ends_the_process_beside(no_process_yet, monkeypatch):
    real = subprocess.Popen
    monkeypatch.setattr(beside.subprocess, "Popen", lambda command, **kwargs: real(
        [sys.executable, "-c", "import time; time.sleep(60)"], **kwargs))
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    assert compile_module.compile_beside(ModelSettings(**TINY), TrainSettings(torch_compile="stacked"), 6)
    process, output = compile_module._beside
    compile_module.stop_beside()
    assert process.returncode is not None and not output.parent.exists()


@pytest.mark.slow  # the process compiles a 2-layer stack with an empty inductor cache: about 30 s on 2 cores
@needs_compiler
def test_the_job_finds_what_the_process_beside_compiled(data, tmp_path, no_process_yet, monkeypatch):
    if torch.get_num_threads() < 2:
        pytest.skip("the process beside starts only where a job has two torch threads")
    conversations, tokenizer = data
    model = ModelSettings(**TINY)
    train = TrainSettings(torch_compile="stacked", batch_threads=2, max_steps=2, **QUIET)
    with temporary_cache_dir(str(tmp_path / "inductor")):
        assert compile_module.compile_beside(model, train, 6)
        compile_module._warmed()
        assert compile_module._beside[0].returncode == 0
        compiled = _fxgraph_entries()
        assert compiled  # the process compiled the stack, forward and backward ...
        finetune(build_scratch_model(tokenizer, model, seed=0), tokenizer, WORD_LEVEL_FORMAT, conversations, train,
                 tmp_path / "job")
        assert _fxgraph_entries() == compiled  # ... and the job's own compile found both in the cache
        torch._dynamo.reset()
