"""How the trainer uses the hardware: bf16 only where the CPU multiplies bf16 in hardware (and, if asked, only
where it measures at least `BF16_MIN_SPEEDUP` times the fp32 rate), and torch.compile scoped as
`TrainSettings.torch_compile` says (regional compilation in place; accelerate's compile environment kept out)."""

from __future__ import annotations

import functools
import logging
import os
import platform
import shutil
import subprocess
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from pipeline.lm.model_settings import ModelSettings
    from pipeline.lm.training.settings import TrainSettings

log = logging.getLogger(__name__)

DYNAMO_ENV_PREFIX = "ACCELERATE_DYNAMO_"


def cpu_has_bf16(cpuinfo: str | None = None) -> bool:
    """Whether this CPU multiplies bf16 matrices in hardware (AVX512-BF16 or AMX on x86; any Arm/Apple CPU
    torch runs bf16 on is trusted). Without it oneDNN emulates bf16, far slower than fp32 (README, Speed)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:  # not Linux: nothing to read, trust torch
            return True
    flags = next((line.split(":", 1)[1].split() for line in cpuinfo.splitlines() if line.startswith("flags")), None)
    if flags is None:  # no x86 flags line (e.g. Arm's "Features"): trust torch
        return True
    return bool({"avx512_bf16", "amx_bf16"} & set(flags))


# On a CPU, bf16 autocast is chosen only where its matmuls are not clearly slower than fp32's: some CPUs with
# AVX512-BF16 multiply bf16 at half their fp32 rate (README, Speed). The margin keeps the choice stable under
# timing noise, so one machine always makes the same one.
BF16_MIN_SPEEDUP = 0.8


def matmul_peak(dtype: torch.dtype, *, device: str = "cpu", size: int | None = None, seconds: float = 0.5) -> float:
    """Best GFLOP/s of square ``dtype`` matmuls over five timed rounds on ``device`` (CPU: torch's current
    threads, 1024^3 products; GPU: 8192^3, synchronised before each clock read)."""
    size = size or (8192 if device == "cuda" else 1024)
    a, b = (torch.randn(size, size, dtype=dtype, device=device) for _ in range(2))
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    for _ in range(3):
        a @ b
    sync()
    best = 0.0
    for _ in range(5):
        n, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds / 5:
            torch.matmul(a, b)
            n += 1
            sync()
        best = max(best, 2 * size**3 * n / (time.perf_counter() - start) / 1e9)
    return best


# The CPU's matmul peaks (fp32, bf16) as `use_bf16` measured them, by torch's number of threads: measured once a
# process, so a job's later steps (and a process compiling beside it: `compile_beside`) take the same decision.
_PEAKS: dict[int, tuple[float, float]] = {}


def use_bf16(requested: bool, when_faster: bool = False) -> bool:
    """bf16 as asked on a GPU. On a CPU, a CPU without bf16 hardware trains in fp32; with ``when_faster``, so
    does one whose bf16 matmuls measure below `BF16_MIN_SPEEDUP` times its fp32 ones (each with a warning
    naming the reason; the peaks measured once a process for each number of threads)."""
    if not requested or torch.cuda.is_available():
        return requested
    if not cpu_has_bf16():
        log.warning("train.bf16=true but this CPU has no bf16 matmul hardware (no avx512_bf16 or amx_bf16 flag): "
                    "training in fp32 instead")
        return False
    if not when_faster:
        return True
    threads = torch.get_num_threads()
    if threads not in _PEAKS:  # 0.2 s each: 0.5 s a job (the ratio moved 2.18-2.20 against 2.19-2.25 over 0.5 s)
        _PEAKS[threads] = matmul_peak(torch.float32, seconds=0.2), matmul_peak(torch.bfloat16, seconds=0.2)
    fp32, bf16 = _PEAKS[threads]
    if bf16 < BF16_MIN_SPEEDUP * fp32:
        log.warning("train.bf16=true but this CPU multiplies bf16 slower than fp32 (matmul peaks on %d threads: bf16 "
                    "%.0f, fp32 %.0f GFLOP/s): training in fp32 instead", torch.get_num_threads(), bf16, fp32)
        return False
    log.info("bf16 autocast: matmul peaks on %d threads: bf16 %.0f, fp32 %.0f GFLOP/s", torch.get_num_threads(),
             bf16, fp32)
    return True


@contextmanager
def dynamo_environment():
    """The environment in which a Trainer is built: no ``ACCELERATE_DYNAMO_*`` variables.

    accelerate's TorchDynamoPlugin, which Trainer builds, takes from these variables whatever Trainer does not
    pass: the backend when ``torch_compile`` is off, and the mode, dynamic shapes and regional compilation
    always. ``accelerate launch`` sets them from its config, and so did TrainingArguments with accelerate
    before 1.2. Left in place, they would compile a job whose ``train.torch_compile`` is ``none`` (or change
    how a ``full`` job compiles): ``train.torch_compile`` alone decides, so a ``dynamo_config`` in an
    accelerate config is not used. Outside this block the variables are as they were.
    """
    saved = {key: value for key, value in os.environ.items() if key.startswith(DYNAMO_ENV_PREFIX)}
    for key in saved:
        del os.environ[key]
    try:
        yield
    finally:
        for key in [key for key in os.environ if key.startswith(DYNAMO_ENV_PREFIX)]:
            del os.environ[key]
        os.environ.update(saved)


_warming: threading.Thread | None = None
_join_checks = True  # whether `compiled_blocks` waits for `_warming` (`warm_compiler`'s wait)


def warm_compiler(wait: bool = True) -> None:
    """Start, in a background thread, what inductor does once per process before its first compile on a CPU: it
    checks which vector instructions the C++ compiler can use by compiling a small program for each (about 7 s of g++
    one after the other on these CPUs with an empty inductor cache, under 4 s side by side, as here; its cache keeps
    the programs, so later processes only load them).
    A job calls this before its data-build, whose Python keeps one core busy while g++ runs on the other;
    `compiled_blocks` waits for it, or with ``wait=False`` compiles meanwhile (dynamo's and AOTAutograd's work
    needs no answer; inductor's asks for it, and a check asked twice is built once: inductor locks each one's
    file). Once per process; nothing where a GPU trains."""
    global _warming, _join_checks
    if _warming is not None or torch.cuda.is_available():
        return
    _join_checks = wait

    # Imported here, on the calling thread: the threads below only run the checks (no imports beside a data-build
    # that forks worker processes).
    from torch._inductor import codecache  # noqa: F401 - the checks' compiler cache, imported before the thread
    from torch._inductor import cpu_vec_isa

    def check() -> None:
        try:
            # Each instruction set this CPU names checked in a thread of its own (one g++ each), not one after the
            # other: 3.7-3.9 s against 6.9-7.1 s on the Zen 4 EPYC with its 3 (README, Speed). Each check's answer
            # is kept per set, so the choice below only reads them.
            flags = cpu_vec_isa.x86_isa_checker() if platform.machine() in ("x86_64", "AMD64") else []
            candidates = [isa for isa in cpu_vec_isa.supported_vec_isa_list
                          if flags and all(flag in flags for flag in str(isa).split())]
            checks = [threading.Thread(target=bool, args=(isa,), daemon=True) for isa in candidates]
            for thread in checks:
                thread.start()
            for thread in checks:
                thread.join()
            cpu_vec_isa.pick_vec_isa()  # cached for the process: the compile that follows asks again, gets the answer
        except Exception as error:  # noqa: BLE001 - the compile itself meets and reports whatever failed here
            log.debug("inductor's vector-instruction checks, ahead of compiling: %s", error)

    _warming = threading.Thread(target=check, name="inductor-isa-checks", daemon=True)
    _warming.start()


# What `compile_beside` started: the process, and where its output goes.
_beside: tuple[subprocess.Popen, Path] | None = None
# The longest a job's first compile waits for the process beside it (it took about 20 s on 2 cores).
BESIDE_TIMEOUT = 300


def compile_beside(model: ModelSettings, train: TrainSettings, frame: int) -> bool:
    """Hand a process of its own this job's settings for one training step of a model shaped as the job's
    (`pipeline.lm.training.precompile`: the process `beside.start_early` started with the command line, which
    has imported meanwhile, or one started now): the decoder layer compiled while the job builds its data, so the
    job's first step finds inductor's caches holding its graphs (about 14 s of the CPU default's first step,
    against about 2 s with those caches; README, Speed). Only where the job would compile its layers on a CPU, a
    model trained from scratch, in this process, on at least two torch threads; otherwise, or the second time in a
    process, the early process is ended and `warm_compiler`'s checks start alone (or nothing). bf16 is decided
    here, for both processes (`use_bf16`). `compiled_blocks` waits for the process; `stop_beside` ends it where
    the job trains nothing. Returns whether a process compiles."""
    global _beside
    from pipeline.lm.model_settings import ModelKind
    from pipeline.lm.training import beside

    early = beside.take()
    threads = train.torch_threads or torch.get_num_threads()  # what the job's training will run on
    if (_beside is not None or _warming is not None or torch.cuda.is_available() or not train.torch_compile.blocks
            or model.kind is not ModelKind.scratch or train.accelerate_config or threads < 2):
        if early is not None:
            beside.send(early[0], None)
        if train.torch_compile.blocks and _beside is None and not torch.cuda.is_available():
            warm_compiler()
        return False
    bf16 = use_bf16(train.bf16, train.bf16_when_faster)  # measured before a process starts beside it
    process, output = early or beside.start()
    beside.send(process, {"model": model.to_dict(), "train": train.to_dict(), "frame": frame, "threads": threads,
                          "bf16": bf16})
    _beside = (process, output)
    return True


def stop_beside() -> None:
    """End `compile_beside`'s process if it still runs (a job whose training was reused needs none of it)."""
    if _beside is not None and _beside[0].poll() is None:
        _beside[0].kill()
        _beside[0].wait()
        shutil.rmtree(_beside[1].parent, ignore_errors=True)


def _warmed() -> None:
    if _warming is not None and _join_checks:
        _warming.join()
    if _beside is not None and _beside[0].returncode is None:
        process, output = _beside
        try:
            process.wait(timeout=BESIDE_TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        if process.returncode == 0:
            shutil.rmtree(output.parent, ignore_errors=True)
        else:
            log.warning("compiling the layer beside the data-build ended with exit status %s (its output: %s); "
                        "compiling it here", process.returncode, output)


@contextmanager
def compile_settings():
    """The compiler's settings `compiled_blocks` traces under. torch keeps them per thread: a thread that may compile
    the blocks (`pipeline.lm.training.parts`) enters this itself. Python floats traced as constants
    (``specialize_float``); sizes not "duck-shaped" (one symbol for equal sizes): with it, a first batch part as
    wide as the hidden size (128 on the CPU default) tied its width to the weights' constant size, so that graph
    was static and the next width compiled again (14 s cold)."""
    with torch._dynamo.config.patch(specialize_float=True), torch.fx.experimental._config.patch(use_duck_shape=False):
        yield


@contextmanager
def compiled_blocks(model: torch.nn.Module, torch_compile: str, release_gil: bool = False):
    """With ``regional``, compile every block of the model's repeated blocks (a decoder's layers: the
    ModuleLists whose members share a class) in place while the block runs, then put them back to eager. With
    ``stacked``, a plain ModuleList of such blocks is compiled as one call that runs them in turn
    (`_StackedBlocks`): one graph for all the layers, fewer calls into compiled code a step (about 0.97x the
    CPU default's step), a longer cold compile (37 s against 26 s on one thread) and the same numbers, as no kernel
    spans two layers (`layer_boundary`; README, Speed).

    In place, so parameter names, checkpoints and the saved model are those of the plain model. Blocks of one
    class share their compiled code, so a 4-layer model compiles one layer, once: with dynamic shapes, one graph
    for every batch width and size above 1 (torch specializes a dimension of 1). Compiled for the first batch's
    shapes, it compiled again at the second width and a third time at an epoch's one short batch (15 s and 20 s
    of the CPU default's job; its steps measured as fast either way). accelerate's regional compilation also
    compiles the small modules around the blocks, each apart; through Trainer that ran slower than eager here.
    Python floats are traced as constants (``specialize_float``): traced as symbols, one of the layer's floats
    made dynamo start the trace over, about 3 s of every cold compile, for the same graph and the same weights
    (`compile_settings`, which the part threads enter too: torch keeps these settings per thread).
    Dynamo's caches are reset afterwards, so the next job in the same process starts under no guards or
    recompile counts of this one (inductor's on-disk cache keeps the compiled kernels). With ``release_gil``
    the compiled graphs run from inductor's C++ wrapper, which releases Python's interpreter lock, so threads
    computing parts of a batch overlap (`pipeline.lm.training.parts`); the kernels are the same. A ModuleList
    whose blocks are compiled apart carries ``compile_region`` meanwhile: a function compiled the way they are,
    once a function (`pipeline.lm.training.last_layer` runs every block through one). It waits for
    `warm_compiler`'s checks, if a job started them.
    """
    if torch_compile not in ("regional", "stacked"):
        yield
        return
    lists = [module for module in model.modules() if isinstance(module, torch.nn.ModuleList) and len(module) > 1
             and len({type(block) for block in module}) == 1]
    options = {"cpp_wrapper": True} if release_gil else None
    stacked = [blocks for blocks in lists if torch_compile == "stacked" and type(blocks) is torch.nn.ModuleList]
    apart = [block for blocks in lists if blocks not in stacked for block in blocks]
    regions = [blocks for blocks in lists if blocks not in stacked]
    compile_region = functools.cache(lambda function: torch.compile(function, dynamic=True, options=options))
    # Compiled calls made (inductor's modules imported: about 1 s) while `compile_beside`'s process may still run.
    for blocks in stacked:
        blocks.__class__ = _StackedBlocks
        blocks._in_turn = torch.compile(_in_turn(list(blocks)), dynamic=True, options=options)
    for block in apart:
        block.compile(dynamic=True, options=options)
    for blocks in regions:
        blocks.compile_region = compile_region
    _warmed()  # the checks `warm_compiler` started (one thread compiles at a time), or the process beside
    try:
        with compile_settings():
            yield
    finally:
        for blocks in stacked:
            blocks.__class__ = torch.nn.ModuleList
            del blocks._in_turn
        for block in apart:
            block._compiled_call_impl = None  # what nn.Module.compile set: calls go to the eager forward again
        for blocks in regions:
            del blocks.compile_region
        torch._dynamo.reset()


@torch.library.custom_op("cogmap::layer_boundary", mutates_args=())
def layer_boundary(hidden_states: torch.Tensor) -> torch.Tensor:
    """A copy of ``hidden_states`` that inductor cannot see into (an operator of its own, run from the compiled
    graph as an outside call), and the same for the gradient that flows back through it: in a graph of several
    layers, the kernels of one layer are not fused with the next one's, forward or backward, so each layer's
    kernels are those of the layer compiled alone and its numbers are the same, bit for bit (`_in_turn`)."""
    return hidden_states.clone()


@layer_boundary.register_fake
def _(hidden_states: torch.Tensor) -> torch.Tensor:
    return torch.empty_like(hidden_states)


layer_boundary.register_autograd(lambda ctx, grad: layer_boundary(grad))


def _in_turn(blocks: list[torch.nn.Module]):
    """One call that runs ``blocks`` in turn, each on the hidden states the one before returned (a transformers 5
    decoder layer's return) with the arguments the model gives every layer; a `layer_boundary` between two."""

    def run(hidden_states, *args, **kwargs):
        for i, block in enumerate(blocks):
            if i:
                hidden_states = layer_boundary(hidden_states)
            hidden_states = block(hidden_states, *args, **kwargs)
        return hidden_states

    return run


class _StackedBlocks(torch.nn.ModuleList):
    """A model's ModuleList of blocks while `compiled_blocks` stacks them: the same modules under the same names
    (state dicts, checkpoints and iteration unchanged), but the slice of all of them, which a transformers model
    loops over in its forward (``self.layers[:num_hidden_layers]``), is the one compiled call that runs them in
    turn."""

    _in_turn: object

    def __getitem__(self, index):
        if isinstance(index, slice) and range(len(self))[index] == range(len(self)):
            return [self._in_turn]
        return super().__getitem__(index)
