"""Training throughput: the plain padded Trainer against ours, and FLOP/s against this machine's matmul peaks.

    python benchmarks/bench_train.py [--data cpu|paper] [--steps 60] [--skip 10] [--threads 2] [--rounds 1]
                                     [--model conf/model/tiny.yaml] [--train conf/train/cpu.yaml]
                                     [--switch all-logits|whole-last-layer|muon-bf16 [--every 5]]

Every run trains the same scratch model (shape from ``--model``, the CPU default unless told) on the same
conversations through `pipeline.lm.training.trainer.finetune`, with the default job's batch size and learning rate:

- ``padded fp32``: the plain Trainer: random batches padded to the longest, an attention mask, fp32, eager.
- ``packed fp32``: our length-grouped batches (right-padded, no mask), fp32, eager.
- ``packed bf16``: the same with bf16 autocast (matmuls on the CPU's AMX/AVX512-BF16 units, fp32 master
  weights; fp32 on a CPU without them), eager.
- ``default``: exactly what ``--train`` sets, its ``torch_compile`` scope included (the CPU default:
  ``regional``). Only when that scope is not ``none``.
- ``default, bf16 when faster``: the same with ``bf16_when_faster`` (`pipeline.lm.training.compile.use_bf16`),
  when that picks another precision on this machine.
- ``default, <optimizer>``: the default with the other ``optimizer`` (``adamw`` or ``muon``,
  `pipeline.lm.training.optim`): what Muon's step costs against AdamW's.
- ``default, Muon's Newton-Schulz in <fp32|bf16>``: the default with the other ``muon_bf16`` (when the default
  trains with Muon in bf16; the CPU default's iterations are bf16, so this run's are fp32): what Muon's iterations
  cost in one precision against the other.
- ``default, <kernel> attention``: the default with the other of ``sdpa`` and ``eager`` for
  ``model.attn_implementation`` (the same attention, computed by torch's fused kernel or as two matmuls and a
  softmax that the compiler fuses): what the attention kernel costs at these short sequences.
- ``default, plain positions``: the default with ``position_stretch`` 1 (when the default stretches its training
  positions, which also sends the attention mask): what stretched positions cost.
- ``default, paper prompt``: the same on the same worlds with the paper's instruction turns, when ``--model``
  prompts with the task turn alone (``prompt: task``, the CPU default): tokens/s barely move, conversations/s
  is what the switch buys.
- ``default, newlines <own|joined|composed>``: the same conversations cut by the tokenizer with another
  ``model.newlines`` (``--other-newlines``; a newline its own token, or joined to the line's last word, with the
  joined words' rows composed or not): fewer tokens a conversation, so compare conversations/s.
- ``default, whole batches``: the default with ``batch_threads`` 1 (when the default cuts each batch into parts
  computed side by side by Python threads): what the parts buy.
- ``default, logits everywhere``: the default with ``labelled_logits`` false (when the default applies the output
  head and the loss at the labelled positions only): what that buys.
- ``default, whole last layer``: the default with ``labelled_last_layer`` false (when the default computes its
  last layer from the first labelled position on): what that buys.

Each run prints two rates: over all its steps (compiling included), and in steady state: the median rate of
the optimizer steps themselves (forward, backward and update: no batch loading or logging) after the first
``--skip`` (compiling, and the kernels oneDNN builds for each new batch width, mostly done). The time the steps
took over the steady rate (compiling, mostly) is printed too. Inductor keeps compiled kernels on disk
(``TORCHINDUCTOR_CACHE_DIR``): a second run compiles from that cache, in a fraction of the time.

``--rounds N`` runs the selection N times, in turn and then reversed (A B, B A, ...), and reports each run's
median over rounds with the steady ratio of every round beside it. One pass can mislead on a machine whose speed
drifts within minutes: on a Zen 4 EPYC (on the earlier data, the job's first worlds), one pass of 80 steps put
Muon's bf16 iterations at 1.19x the default, the next pass of 150 steps at 1.05x; four rounds of 120 steps gave
1.14x, 1.09x, 1.16x and 1.14x, while the default's own rate fell by a quarter from the first round to the last
(docs/speed.md).

``--switch NAME`` runs one run instead: the default, taking the NAME run's value of that one setting every other
``--every`` steps (a setting the trainer or its optimizer reads at every step: the head everywhere, the whole last
layer, Muon's iterations in the other precision). Both values meet the same drift, so an effect of a few percent
shows, where runs in turn did not resolve one: on an AVX2-only Zen 3 draw four rounds put the whole last layer at
0.89x to 1.09x the cut's rate, and runs switching it every 10 steps at 0.94x and 0.95x (docs/speed.md). It prints
each value's median rate over its own steady steps and their ratio over the steady state and over each half of it
(their spread is the noise's size).

``--data cpu`` (the default) is what the default job trains on: BWD marking-deadend conversations of 2..4-cell
worlds (80-230 tokens with the default's cut). ``--data paper``: FWD conversations of 300-1,500 tokens, where
padding costs more.

tokens/s counts real tokens. Achieved FLOP/s counts useful work only (6N per token plus causal attention,
padding excluded), so it compares with a matmul peak. Peaks (fp32 and bf16 matmuls: 1024^3 on a CPU,
8192^3 on a GPU, where the Trainer then trains) are measured before and after the runs, because this machine
is shared and its speed moves; the best is used. A CPU without bf16 hardware has no bf16 peak (emulated at about
1 GFLOP/s): there only the fp32 peak is measured and the shares are of it.
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch
import transformers
from omegaconf import OmegaConf
from transformers import TrainerCallback

from pipeline.lm.chat import WORD_LEVEL_FORMAT, encode_conversation
from pipeline.lm.model_settings import NEWLINES, ModelSettings
from pipeline.workflow.data_build import DataSettings
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.compile import cpu_has_bf16, matmul_peak, use_bf16
from pipeline.lm.training.trainer import finetune
from pipeline.core.generators import generate_worlds
from pipeline.lm.models import make_model
from flops import count_parameters, training_flops
from pipeline.core.texts import conversation
from pipeline.lm.tokenizer import build_word_tokenizer

ROOT = Path(__file__).resolve().parents[1]


# Training runs where the Trainer puts it: the GPU when there is one. Peaks are measured on that device.
DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def peaks(threads: int) -> dict[str, float]:
    """The matmul peaks (GFLOP/s) of fp32 and, where bf16 runs in hardware, of bf16. A CPU without bf16
    hardware emulates it at about 1 GFLOP/s: no peak to compare a run with, and about 18 s a measurement."""
    torch.set_num_threads(threads)
    kinds = {"fp32": torch.float32}
    if DEVICE == "cuda" or cpu_has_bf16():
        kinds["bf16"] = torch.bfloat16
    return {kind: matmul_peak(dtype, device=DEVICE, seconds=2.0) for kind, dtype in kinds.items()}


def device_line(threads: int) -> str:
    if DEVICE == "cuda":
        return f"gpu: {torch.cuda.get_device_name()}; torch {torch.__version__}"
    return f"cpu: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; torch {torch.__version__}, {threads} threads"


def best_peaks(measured: list[dict[str, float]], threads: int) -> dict[str, float]:
    """The peaks measured once more after the runs (appended to ``measured``, printed) and the best of each kind:
    this machine's speed moves during a benchmark."""
    measured.append(peaks(threads))
    best = {k: max(m[k] for m in measured) for k in measured[0]}
    print("matmul peak after: " + ", ".join(f"{k} {v:.1f} GFLOP/s" for k, v in measured[-1].items())
          + "; using the best: " + ", ".join(f"{k} {v:.1f}" for k, v in best.items()))
    return best


def shares(rate: float, flops_per_token: float, peak: dict[str, float]) -> str:
    """``rate`` real tokens/s of ``flops_per_token`` useful FLOPs as a share of each peak."""
    return ", ".join(f"{100 * rate * flops_per_token / 1e9 / value:.0f}% of the {kind} peak"
                     for kind, value in peak.items())


class StepClock(TrainerCallback):
    """Wall time and real tokens of every optimizer step."""

    def __init__(self):
        self.steps: list[tuple[float, int]] = []
        self._start, self._tokens = 0.0, 0

    def on_step_begin(self, args, state, control, **kwargs):
        self._start = time.perf_counter()

    def on_step_end(self, args, state, control, **kwargs):
        self.steps.append((time.perf_counter() - self._start, state.num_input_tokens_seen - self._tokens))
        self._tokens = state.num_input_tokens_seen

    def steady(self, skip: int) -> float:
        """Median real tokens per second of the steps after the first ``skip``: a step that compiles for a new
        shape, or that a neighbour on this shared machine slowed, does not move it."""
        return statistics.median(n / t for t, n in self.steps[skip:])


# What --switch flips between the steps of one run: a setting the trainer (or its optimizer) reads at every step,
# as (what holds it, its attribute, the other run's value given the default's).
SWITCHES = {
    "all-logits": (lambda trainer: trainer, "labelled_logits", lambda value: not value),
    "whole-last-layer": (lambda trainer: trainer, "labelled_last_layer", lambda value: not value),
    "muon-bf16": (lambda trainer: trainer.optimizer, "ns_dtype",
                  lambda value: torch.float32 if value == torch.bfloat16 else torch.bfloat16),
}


def _unswitchable(name: str, train: TrainSettings, precision: str) -> str | None:
    """Why the default (``train``, training in ``precision`` here) has no ``name`` run to switch to, or None."""
    if name == "all-logits" and not train.labelled_logits:
        return "the train yaml computes the logits everywhere already (labelled_logits: false)"
    if name == "whole-last-layer" and not (train.labelled_logits and train.labelled_last_layer):
        return "the train yaml computes the whole last layer already (labelled_last_layer or labelled_logits false)"
    if name == "muon-bf16" and (train.optimizer != "muon" or precision != "bf16"):
        return (f"Muon's iterations have a precision to choose only where the default trains with Muon in bf16; "
                f"here: {train.optimizer}, {precision}")
    return None


class Switcher(StepClock):
    """A `StepClock` for one run that takes the default's value of a `SWITCHES` setting and the other run's in
    turns of ``every`` steps (the default's first), and records which one each step ran with."""

    def __init__(self, name: str, every: int):
        super().__init__()
        self._holder_of, self.attribute, self._other_value = SWITCHES[name]
        self.every = every
        self.holder = None  # what holds the setting: the bound trainer, or its optimizer
        self.switched: list[bool] = []  # each timed step: whether it ran the other run's value
        self._values: tuple = ()
        self._now = False

    def bind(self, trainer) -> None:
        """`finetune` hands over its trainer before training starts."""
        self.holder = self._holder_of(trainer)
        default = getattr(self.holder, self.attribute)
        self._values = (default, self._other_value(default))

    def on_step_begin(self, args, state, control, **kwargs):
        if not self._values:
            raise RuntimeError("Switcher: no trainer bound (finetune binds it before training starts)")
        self._now = (state.global_step // self.every) % 2 == 1
        setattr(self.holder, self.attribute, self._values[self._now])
        super().on_step_begin(args, state, control, **kwargs)

    def on_step_end(self, args, state, control, **kwargs):
        super().on_step_end(args, state, control, **kwargs)
        self.switched.append(self._now)

    def steady_of(self, skip: int, switched: bool, steps: range | None = None) -> tuple[float, float, int]:
        """Median real tokens per second and median seconds of the steps after the first ``skip`` (of ``steps``,
        if given) that ran with the other value (``switched``) or the default's, and how many there were."""
        picked = [self.steps[i] for i in (steps or range(skip, len(self.steps))) if self.switched[i] == switched]
        return statistics.median(n / t for t, n in picked), statistics.median(t for t, _ in picked), len(picked)


def switching(args, train, other: str, default: str, per_token: dict, per_conversation: dict,
              measured: list) -> None:
    """``--switch``: one run of the default that takes the ``other`` run's setting every other ``--every`` steps.
    Both settings meet the same drift, so a difference of a few percent shows (runs in turn did not resolve one on
    these machines: docs/speed.md). Prints each setting's steady rate, their ratio over the whole steady state
    and over each half of it (their spread is the noise's size), and the shares of the matmul peaks."""
    clock = Switcher(args.switch, args.every)
    result = train(default, clock)
    per_token[other], per_conversation[other] = per_token[default], per_conversation[default]
    print(f"{default}, switched to '{other.removeprefix(default + ', ')}' every {args.every} steps: "
          f"{result.tokens_per_second:.0f} real tokens/s over all steps; {result.train_seconds:.1f} s for "
          f"{result.global_step} steps; final loss {result.final_loss:.3f}")
    rates = {}
    for name, switched in ((default, False), (other, True)):
        rate, seconds, count = clock.steady_of(args.skip, switched)
        rates[name] = rate
        print(f"{name}: {rate:.0f} real tokens/s in steady state ({rate * per_token[name] / 1e9:.1f} GFLOP/s "
              f"useful; {rate / per_conversation[name]:.1f} conversations/s), {1000 * seconds:.1f} ms a step "
              f"(medians of its {count} steps after step {args.skip})")
    middle = (args.skip + len(clock.steps)) // 2
    halves = [clock.steady_of(args.skip, True, half)[0] / clock.steady_of(args.skip, False, half)[0]
              for half in (range(args.skip, middle), range(middle, len(clock.steps)))]
    print(f"{other} / {default} tokens/s in steady state, switched within one run: "
          f"{rates[other] / rates[default]:.3f}x (halves of the steady state: {halves[0]:.3f}x, {halves[1]:.3f}x)")
    peak = best_peaks(measured, args.threads)
    for name, rate in rates.items():
        print(f"{name}: steady state {shares(rate, per_token[name], peak)}")


def preset(settings_class, path):
    """A preset yaml as the job reads it: what it lists, merged onto its settings class's defaults."""
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(settings_class), OmegaConf.load(path)))


@functools.lru_cache(maxsize=2)
def _cpu_train_worlds(n: int, seed: int) -> list:
    """The default job's train worlds (at least ``n``), generated once for both prompts' sets (about 7 s)."""
    data = preset(DataSettings, ROOT / "conf" / "data" / "cpu.yaml")
    return generate_worlds(max(n, data.n_train), seed, data.generator_config("train"))


def cpu_conversations(n: int, seed: int, prompt: str, plan: str = "moves") -> list[list[dict]]:
    """What the default job trains on (conf/data/cpu.yaml; BWD marking-deadend, optimal setting; ``plan``: the
    model's Plan form): ``n`` of the job's ``n_train`` distinct worlds, evenly spaced over them. Not the first
    ``n``: distinct worlds run out of small ones as the stream goes on, so its conversations grow longer (the
    default's: 136 tokens on average in the first tenth, 165 in the last, 154.6 over all 50,000)."""
    worlds = _cpu_train_worlds(n, seed)
    return [conversation(worlds[i * len(worlds) // n], "bwd", "marking-deadend", "optimal", prompt=prompt, plan=plan)
            for i in range(n)]


def paper_conversations(n: int, seed: int, prompt: str, plan: str = "moves", low: int = 300, high: int = 1500
                        ) -> list[list[dict]]:
    """``n`` FWD marking-deadend conversations of paper-size worlds whose word-level length is in [low, high]."""
    texts = [conversation(w, "fwd", "marking-deadend", "optimal", prompt=prompt, plan=plan)
             for w in generate_worlds(3 * n, seed)]
    tokenizer = build_word_tokenizer(t["value"] for c in texts for t in c)
    kept = [c for c in texts if low <= len(encode_conversation(tokenizer, WORD_LEVEL_FORMAT, c)[0]) <= high]
    if len(kept) < n:
        raise SystemExit(f"only {len(kept)} conversations of {low}-{high} tokens among {len(texts)}")
    return kept[:n]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", choices=("cpu", "paper"), default="cpu")
    parser.add_argument("--conversations", type=int, default=600)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--skip", type=int, default=10, help="steps left out of the steady-state rate")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--model", default=str(ROOT / "conf" / "model" / "tiny.yaml"), help="a scratch model yaml")
    parser.add_argument("--train", default=str(ROOT / "conf" / "train" / "cpu.yaml"), help="a train yaml")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rounds", type=int, default=1,
                        help="run the selected runs this many times, in turn and reversed (ABBA): drift cancels")
    parser.add_argument("--other-newlines", choices=NEWLINES, default=None,
                        help="the other-newlines run's cut (default: joined, or own if the model joins them)")
    parser.add_argument("--only", choices=("padded-fp32", "packed-fp32", "packed-bf16", "default", "when-faster",
                                           "default, paper prompt", "other-optimizer", "muon-bf16",
                                           "other-attention", "plain-positions", "other-newlines", "whole-batches",
                                           "all-logits", "whole-last-layer"),
                        action="append", help="run only these (repeatable)")
    parser.add_argument("--switch", choices=tuple(SWITCHES), default=None,
                        help="one run of the default that flips to this run's setting every --every steps")
    parser.add_argument("--every", type=int, default=5, help="steps between two flips of --switch")
    args = parser.parse_args()
    if not 0 <= args.skip < args.steps:
        parser.error(f"--skip {args.skip} must be at least 0 and below --steps {args.steps}")
    if args.rounds < 1:
        parser.error(f"--rounds {args.rounds} must be at least 1")
    if args.switch:
        if args.only or args.rounds != 1:
            parser.error(f"--switch {args.switch} is one run of its own: not with --only or --rounds")
        if args.every < 1 or args.skip < 2 * args.every or args.steps < args.skip + 4 * args.every:
            parser.error(f"--switch needs --every >= 1, --skip >= 2 x --every (each setting compiled before the "
                         f"steady state) and --steps >= --skip + 4 x --every (each in each half of it); got --every "
                         f"{args.every}, --skip {args.skip}, --steps {args.steps}")
    transformers.logging.set_verbosity_error()

    model_cfg, train_cfg = preset(ModelSettings, args.model), preset(TrainSettings, args.train)
    # What the trainer will choose on this machine (on the runs' threads), as --train asks and with bf16_when_faster.
    torch.set_num_threads(args.threads)
    precision = "bf16" if use_bf16(train_cfg.bf16, train_cfg.bf16_when_faster) else "fp32"
    faster = "bf16" if use_bf16(train_cfg.bf16, True) else "fp32"
    if args.switch and (missing := _unswitchable(args.switch, train_cfg, precision)):
        parser.error(f"--switch {args.switch}: {missing}")
    make = cpu_conversations if args.data == "cpu" else paper_conversations
    prompt = model_cfg.prompt
    sets = {prompt: make(args.conversations, args.seed, prompt, model_cfg.plan_form)}
    if prompt != "paper":  # the same worlds with the paper's instruction turns: what the prompt switch saves
        sets["paper"] = make(args.conversations, args.seed, "paper", model_cfg.plan_form)
    conversations = sets[prompt]
    texts_seen = [t["value"] for c in [*sets.get("paper", []), *conversations] for t in c]
    other_newlines = args.other_newlines or ("joined" if model_cfg.newlines == "own" else "own")
    if other_newlines == model_cfg.newlines:
        parser.error(f"--other-newlines {other_newlines} is the model's own (newlines: {model_cfg.newlines})")
    tokenizers = {newlines: build_word_tokenizer(texts_seen, numbers=model_cfg.numbers, newlines=newlines,
                                                 spaces=model_cfg.spaces)
                  for newlines in (model_cfg.newlines, other_newlines)}
    tokenizer = tokenizers[model_cfg.newlines]
    lengths = [len(encode_conversation(tokenizer, WORD_LEVEL_FORMAT, c)[0]) for c in conversations]
    probe = make_model(model_cfg, tokenizer, seed=args.seed)
    flops_per_real_token = training_flops(probe, lengths) / sum(lengths)
    scope = train_cfg.torch_compile.value
    print(device_line(args.threads))
    print(f"data ({args.data}, prompt {prompt}, newlines {model_cfg.newlines}, spaces {model_cfg.spaces}): "
          f"{len(conversations)} conversations, "
          f"tokens min {min(lengths)} "
          f"median {statistics.median(lengths):.0f} mean {statistics.fmean(lengths):.0f} max {max(lengths)}; vocab "
          f"{len(tokenizer)}")
    print(f"model ({Path(args.model).name}): {count_parameters(probe) / 1e6:.3f}M parameters, hidden "
          f"{model_cfg.hidden_size} x {model_cfg.num_layers} layers, {model_cfg.num_heads} heads of "
          f"{model_cfg.hidden_size // model_cfg.num_heads}, attention {model_cfg.attn_implementation}; "
          f"{flops_per_real_token / 1e6:.2f} MFLOP per real token (training)")
    print(f"train ({Path(args.train).name}): batch {train_cfg.per_device_batch_size}, lr {train_cfg.learning_rate}, "
          f"precision {precision}, torch_compile {scope}; {args.steps} steps a run, steady state from step "
          f"{args.skip + 1}")

    measured = [peaks(args.threads)]
    print("matmul peak before: " + ", ".join(f"{k} {v:.1f} GFLOP/s" for k, v in measured[0].items())
          + ("" if "bf16" in measured[0] else "; bf16 not measured (no bf16 hardware: emulated)"))
    # name: (packing, bf16, bf16_when_faster, torch_compile, prompt, optimizer, muon_bf16)
    base, ns_bf16 = train_cfg.optimizer, train_cfg.muon_bf16
    runs = {"padded-fp32": (False, False, False, "none", prompt, base, ns_bf16),
            "packed-fp32": (True, False, False, "none", prompt, base, ns_bf16),
            "packed-bf16": (True, True, False, "none", prompt, base, ns_bf16)}
    default = f"default ({precision}, {scope} compile)" if scope != "none" else f"packed-{precision}"
    when_faster = f"default, bf16 when faster ({faster}, {scope} compile)"
    if scope != "none":
        runs[default] = (True, train_cfg.bf16, train_cfg.bf16_when_faster, scope, prompt, base, ns_bf16)
        if faster != precision:
            runs[when_faster] = (True, train_cfg.bf16, True, scope, prompt, base, ns_bf16)
    if "paper" in sets and prompt != "paper":
        runs["default, paper prompt"] = (*runs[default][:4], "paper", base, ns_bf16)
    # What the optimizer's own step costs: the default with the other optimizer (train.optimizer).
    other = "adamw" if base == "muon" else "muon"
    other_optimizer = f"{default}, {other}"
    runs[other_optimizer] = (*runs[default][:5], other, False)
    # What Muon's Newton-Schulz iterations cost in the other precision (only where the default trains in bf16).
    muon_other = f"{default}, Muon's Newton-Schulz in {'fp32' if ns_bf16 else 'bf16'}"
    if base == "muon" and precision == "bf16":
        runs[muon_other] = (*runs[default][:6], not ns_bf16)
    # What the attention kernel costs: the default with the other of sdpa and eager (log-length scaling is sdpa's).
    attention: dict[str, str] = {}  # name: model.attn_implementation where it is not the model yaml's
    other_attention = {"sdpa": "eager", "eager": "sdpa"}.get(model_cfg.attn_implementation)
    attention_run = f"{default}, {other_attention} attention"
    if other_attention and model_cfg.attention_scale == "constant":
        runs[attention_run] = runs[default]
        attention[attention_run] = other_attention
    # The default's family (every run named "default...") trains as --train sets each switch below; the padded and
    # packed baselines keep plain positions, whole batches and logits everywhere. Each run below changes one switch.
    # What stretched positions cost (train.position_stretch; they send the attention mask): the default without.
    stretch: dict[str, float] = {}  # name: position_stretch where it is not the family's
    plain_positions = f"{default}, plain positions"
    if scope != "none" and train_cfg.position_stretch > 1:
        runs[plain_positions] = runs[default]
        stretch[plain_positions] = 1.0
    # What the tokenizer's newlines cost (model.newlines): the default's conversations cut the other way.
    newlines_run = f"{default}, newlines {other_newlines}"
    if scope != "none":
        runs[newlines_run] = runs[default]
    run_newlines = {newlines_run: other_newlines}  # name: model.newlines where it is not the model yaml's
    # What cutting each batch into parts computed side by side buys (train.batch_threads): the default uncut.
    parts: dict[str, int] = {}  # name: batch_threads where it is not the family's
    whole_batches = f"{default}, whole batches"
    if scope != "none" and train_cfg.batch_threads > 1:
        runs[whole_batches] = runs[default]
        parts[whole_batches] = 1
    # What the head and loss at the labelled positions only buy (train.labelled_logits): the default at every one.
    labelled: dict[str, bool] = {}  # name: labelled_logits where it is not the family's
    all_logits = f"{default}, logits everywhere"
    if scope != "none" and train_cfg.labelled_logits:
        runs[all_logits] = runs[default]
        labelled[all_logits] = False
    # What the last layer from the first labelled position on buys (train.labelled_last_layer): the default without.
    last: dict[str, bool] = {}  # name: labelled_last_layer where it is not the family's
    whole_last_layer = f"{default}, whole last layer"
    if scope != "none" and train_cfg.labelled_last_layer:
        runs[whole_last_layer] = runs[default]
        last[whole_last_layer] = False

    def switch(name: str, overrides: dict, family_value, baseline_value):
        """A run's value of one switch: its own, else the family's (--train) or the baselines'."""
        return overrides.get(name, family_value if name.startswith("default") else baseline_value)

    selected = {"default": default, "when-faster": when_faster, "other-optimizer": other_optimizer,
                "muon-bf16": muon_other, "other-attention": attention_run, "plain-positions": plain_positions,
                "other-newlines": newlines_run, "whole-batches": whole_batches,
                "all-logits": all_logits, "whole-last-layer": whole_last_layer}
    wanted = {selected.get(name, name) for name in args.only or runs}
    rounds: dict[str, list[tuple[float, float]]] = {}  # name: (overall, steady) real tokens/s of each round
    per_token: dict[str, float] = {}  # name: useful training FLOPs per real token of its conversations
    per_conversation: dict[str, float] = {}  # name: mean real tokens a conversation
    chosen = [name for name in runs if name in wanted]
    # Round k runs the selection in turn, round k+1 reversed (A B, B A, ...): a machine whose speed drifts steadily
    # during the benchmark favours no run. Only the very first run compiles cold; --skip leaves that out.
    schedule = [(k, name) for k in range(args.rounds) for name in (chosen if k % 2 == 0 else chosen[::-1])]

    def train(name: str, clock: StepClock):
        """One run: ``name``'s settings trained through `finetune`, timed by ``clock``."""
        packing, bf16, bf16_when_faster, compile_scope, run_prompt, optimizer, muon_bf16 = runs[name]
        texts = sets[run_prompt]
        newlines = run_newlines.get(name, model_cfg.newlines)
        run_tokenizer = tokenizers[newlines]
        run_lengths = [len(encode_conversation(run_tokenizer, WORD_LEVEL_FORMAT, c)[0]) for c in texts]
        run_model = replace(model_cfg, attn_implementation=attention.get(name, model_cfg.attn_implementation),
                            newlines=newlines)
        run_probe = probe if newlines == model_cfg.newlines else make_model(run_model, run_tokenizer, seed=args.seed)
        per_token[name] = training_flops(run_probe, run_lengths) / sum(run_lengths)
        per_conversation[name] = statistics.fmean(run_lengths)
        settings = TrainSettings(
            max_steps=args.steps, per_device_batch_size=train_cfg.per_device_batch_size,
            learning_rate=train_cfg.learning_rate, packing=packing, bf16=bf16, bf16_when_faster=bf16_when_faster,
            pad_to_multiple_of=train_cfg.pad_to_multiple_of,
            report_to=(), logging_steps=args.steps, save_steps=10 * args.steps, torch_threads=args.threads,
            torch_compile=compile_scope, optimizer=optimizer, muon_bf16=muon_bf16,
            position_stretch=switch(name, stretch, train_cfg.position_stretch, 1.0),
            batch_threads=switch(name, parts, train_cfg.batch_threads, 1),
            labelled_logits=switch(name, labelled, train_cfg.labelled_logits, False),
            labelled_last_layer=switch(name, last, train_cfg.labelled_last_layer, False),
        )
        with tempfile.TemporaryDirectory() as out:
            model = make_model(run_model, run_tokenizer, seed=args.seed)
            return finetune(model, run_tokenizer, WORD_LEVEL_FORMAT, texts, settings, out, seed=args.seed,
                            max_length=max(run_lengths), callbacks=[clock])

    if args.switch:
        switching(args, train, selected[args.switch], default, per_token, per_conversation, measured)
        return
    for k, name in schedule:
        clock = StepClock()
        result = train(name, clock)
        steady, mean_tokens = clock.steady(args.skip), per_conversation[name]
        rounds.setdefault(name, []).append((result.tokens_per_second, steady))
        # Steady time for all the steps, against the time they took: what compiling (or warming up) cost.
        tokens = sum(n for _, n in clock.steps)
        warmup = sum(t for t, _ in clock.steps) - tokens / steady
        label = f"{name} (round {k + 1})" if args.rounds > 1 else name
        print(f"{label}: {result.tokens_per_second:.0f} real tokens/s over all steps, {steady:.0f} in steady "
              f"state ({steady * per_token[name] / 1e9:.1f} GFLOP/s useful; {steady / mean_tokens:.1f} "
              f"conversations/s of {mean_tokens:.0f} tokens); real-token fraction "
              f"{result.real_token_fraction:.3f}; {result.train_seconds:.1f} s for {result.global_step} steps, "
              f"{warmup:.1f} s of them over the steady rate; final loss {result.final_loss:.3f}")
    peak = best_peaks(measured, args.threads)
    # Over rounds: the median of each run's rates (one round: its rates).
    rates = {name: tuple(statistics.median(r[i] for r in measured_rounds) for i in (0, 1))
             for name, measured_rounds in rounds.items()}
    for base in ("padded-fp32", default):
        if base not in rates:
            continue
        base_all, base_steady = rates[base]
        for name, (overall, steady) in rates.items():
            if name != base:
                conversations = per_conversation[base] / per_conversation[name]  # tokens/s to conversations/s
                each = ""
                if args.rounds > 1:  # the steady ratio of each round: its spread is the drift's size
                    each = " (rounds: " + ", ".join(f"{b[1] / a[1]:.2f}x" for a, b in
                                                    zip(rounds[base], rounds[name])) + ")"
                print(f"{name} / {base} tokens/s: {overall / base_all:.2f}x over all steps, "
                      f"{steady / base_steady:.2f}x in steady state{each}; conversations/s: "
                      f"{conversations * overall / base_all:.2f}x and {conversations * steady / base_steady:.2f}x")
    for name, (overall, steady) in rates.items():
        print(f"{name}: steady state {shares(steady, per_token[name], peak)}; over all steps "
              f"{shares(overall, per_token[name], peak)}")


if __name__ == "__main__":
    main()
