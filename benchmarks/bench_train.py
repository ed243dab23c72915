"""Training throughput: the plain padded Trainer against ours, and FLOP/s against this machine's matmul peaks.

    python benchmarks/bench_train.py [--data cpu|paper] [--steps 20] [--threads 2]
                                     [--model conf/model/tiny.yaml] [--train conf/train/cpu.yaml]

Every run trains the same scratch model (shape from ``--model``, the CPU default unless told) on the same
conversations through `pipeline.finetune.finetune`, with the default job's batch size and learning rate:

- ``padded fp32``: the plain Trainer: random batches padded to the longest, an attention mask, fp32.
- ``packed fp32``: our length-grouped batches (right-padded, no mask), fp32.
- ``packed <default>``: the same at the precision of ``--train`` (the CPU default trains with bf16 autocast,
  which runs matmuls on the CPU's AMX/AVX512-BF16 units and keeps fp32 master weights).

``--data cpu`` (the default) is what the default job trains on: BWD marking-deadend conversations of 2..4-cell
worlds (about 300-480 tokens). ``--data paper``: FWD conversations of 300-1,500 tokens, where padding costs more.

tokens/s counts real tokens. Achieved FLOP/s counts useful work only (6N per token plus causal attention,
padding excluded), so it compares with a matmul peak. Peaks (fp32 and bf16 matmuls: 1024^3 on a CPU,
8192^3 on a GPU, where the Trainer then trains) are measured before and after the runs, because this machine
is shared and its speed moves; the best is used.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch
import transformers
from omegaconf import OmegaConf

from pipeline.chat import WORD_LEVEL_FORMAT, encode_conversation
from pipeline.finetune import TrainSettings, finetune
from pipeline.generate import GeneratorConfig, generate_worlds
from pipeline.modeling import build_scratch_model, count_parameters, training_flops
from pipeline.texts import conversation
from pipeline.tokenizer import build_word_tokenizer

ROOT = Path(__file__).resolve().parents[1]


# Training runs where the Trainer puts it: the GPU when there is one. Peaks are measured on that device.
DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def matmul_peak(threads: int, dtype: torch.dtype, size: int | None = None, seconds: float = 2.0) -> float:
    """Best GFLOP/s of square ``dtype`` matmuls over a few timed rounds (CPU: on ``threads`` threads; GPU:
    8192^3 products, synchronised before each clock read)."""
    torch.set_num_threads(threads)
    size = size or (8192 if DEVICE == "cuda" else 1024)
    a, b = (torch.randn(size, size, dtype=dtype, device=DEVICE) for _ in range(2))
    sync = torch.cuda.synchronize if DEVICE == "cuda" else (lambda: None)
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


def peaks(threads: int) -> dict[str, float]:
    return {"fp32": matmul_peak(threads, torch.float32), "bf16": matmul_peak(threads, torch.bfloat16)}


def device_line(threads: int) -> str:
    if DEVICE == "cuda":
        return f"gpu: {torch.cuda.get_device_name()}; torch {torch.__version__}"
    return f"cpu: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; torch {torch.__version__}, {threads} threads"


def cpu_conversations(n: int, seed: int) -> list[list[dict]]:
    """What the default job trains on (conf/data/cpu.yaml sizes; BWD marking-deadend, optimal setting)."""
    data = OmegaConf.load(ROOT / "conf" / "data" / "cpu.yaml")
    gen = GeneratorConfig(size_x=tuple(data.train_size_x), size_y=tuple(data.train_size_y), frame=data.frame,
                          p_pit=tuple(data.p_pit))
    return [conversation(w, "bwd", "marking-deadend", "optimal") for w in generate_worlds(n, seed, gen)]


def paper_conversations(n: int, seed: int, low: int = 300, high: int = 1500) -> list[list[dict]]:
    """``n`` FWD marking-deadend conversations of paper-size worlds whose word-level length is in [low, high]."""
    texts = [conversation(w, "fwd", "marking-deadend", "optimal") for w in generate_worlds(3 * n, seed)]
    tokenizer = build_word_tokenizer(t["value"] for c in texts for t in c)
    kept = [c for c in texts if low <= len(encode_conversation(tokenizer, WORD_LEVEL_FORMAT, c)[0]) <= high]
    if len(kept) < n:
        raise SystemExit(f"only {len(kept)} conversations of {low}-{high} tokens among {len(texts)}")
    return kept[:n]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", choices=("cpu", "paper"), default="cpu")
    parser.add_argument("--conversations", type=int, default=600)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--model", default=str(ROOT / "conf" / "model" / "tiny.yaml"), help="a scratch model yaml")
    parser.add_argument("--train", default=str(ROOT / "conf" / "train" / "cpu.yaml"), help="a train yaml")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", choices=("padded-fp32", "packed-fp32", "packed-default", "packed-compiled"),
                        action="append", help="run only these (repeatable)")
    parser.add_argument("--compile", action="store_true",
                        help="also run packed-compiled: packed-default with train.torch_compile (its compile time "
                             "counts in tokens/s; inductor's on-disk cache makes a second run's compile shorter)")
    args = parser.parse_args()
    transformers.logging.set_verbosity_error()

    model_cfg, train_cfg = OmegaConf.load(args.model), OmegaConf.load(args.train)
    make = cpu_conversations if args.data == "cpu" else paper_conversations
    conversations = make(args.conversations, args.seed)
    tokenizer = build_word_tokenizer(t["value"] for c in conversations for t in c)
    lengths = [len(encode_conversation(tokenizer, WORD_LEVEL_FORMAT, c)[0]) for c in conversations]
    model_kwargs = dict(hidden_size=model_cfg.hidden_size, num_layers=model_cfg.num_layers,
                        num_heads=model_cfg.num_heads, intermediate_size=model_cfg.intermediate_size,
                        attn_implementation=model_cfg.get("attn_implementation", "sdpa"),
                        max_length=max(lengths), seed=args.seed)
    probe = build_scratch_model(tokenizer, **model_kwargs)
    flops_per_real_token = training_flops(probe, lengths) / sum(lengths)
    default = "bf16" if train_cfg.bf16 else "fp32"
    print(device_line(args.threads))
    print(f"data ({args.data}): {len(conversations)} conversations, tokens min {min(lengths)} median "
          f"{statistics.median(lengths):.0f} max {max(lengths)}; vocab {len(tokenizer)}")
    print(f"model ({Path(args.model).name}): {count_parameters(probe) / 1e6:.3f}M parameters, hidden "
          f"{model_cfg.hidden_size} x {model_cfg.num_layers} layers, {model_cfg.num_heads} heads of "
          f"{model_cfg.hidden_size // model_cfg.num_heads}, attention {model_kwargs['attn_implementation']}; "
          f"{flops_per_real_token / 1e6:.2f} MFLOP per real token (training)")
    print(f"train ({Path(args.train).name}): batch {train_cfg.per_device_batch_size}, lr {train_cfg.learning_rate}, "
          f"default precision {default}; {args.steps} steps a run")

    measured = [peaks(args.threads)]
    print("matmul peak before: " + ", ".join(f"{k} {v:.1f} GFLOP/s" for k, v in measured[0].items()))
    runs = {"padded-fp32": (False, False, False), "packed-fp32": (True, False, False),
            "packed-default": (True, bool(train_cfg.bf16), False)}
    if args.compile:
        runs["packed-compiled"] = (True, bool(train_cfg.bf16), True)
    results = {}
    for name, (packing, bf16, compiled) in runs.items():
        if args.only and name not in args.only:
            continue
        settings = TrainSettings(
            max_steps=args.steps, per_device_batch_size=train_cfg.per_device_batch_size,
            learning_rate=train_cfg.learning_rate, packing=packing, bf16=bf16, max_length=max(lengths),
            pad_to_multiple_of=train_cfg.pad_to_multiple_of,
            report_to=(), logging_steps=args.steps, save_steps=10 * args.steps, torch_threads=args.threads,
            seed=args.seed, torch_compile=compiled,
        )
        with tempfile.TemporaryDirectory() as out:
            model = build_scratch_model(tokenizer, **model_kwargs)
            result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, settings, out)
        results[name] = result
        label = name.replace("default", default)
        print(f"{label:>12}: {result.tokens_per_second:8.0f} real tokens/s, real-token fraction "
              f"{result.real_token_fraction:.3f}, {result.tokens_per_second * flops_per_real_token / 1e9:.1f} "
              f"GFLOP/s useful ({result.train_seconds:.1f} s for {result.global_step} steps, final loss "
              f"{result.final_loss:.3f})")
    measured.append(peaks(args.threads))
    peak = {k: max(m[k] for m in measured) for k in measured[0]}
    print("matmul peak after: " + ", ".join(f"{k} {v:.1f} GFLOP/s" for k, v in measured[1].items())
          + "; using the best: " + ", ".join(f"{k} {v:.1f}" for k, v in peak.items()))
    if "padded-fp32" in results:
        base = results["padded-fp32"].tokens_per_second
        for name in ("packed-fp32", "packed-default", "packed-compiled"):
            if name in results:
                print(f"{name.replace('default', default)} / padded-fp32 tokens/s: "
                      f"{results[name].tokens_per_second / base:.2f}x")
    for name, result in results.items():
        gflops = result.tokens_per_second * flops_per_real_token / 1e9
        print(f"{name.replace('default', default)}: {100 * gflops / peak['fp32']:.0f}% of the fp32 peak, "
              f"{100 * gflops / peak['bf16']:.0f}% of the bf16 peak")


if __name__ == "__main__":
    main()
