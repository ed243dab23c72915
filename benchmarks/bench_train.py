"""Training throughput: the plain padded Trainer against our length-grouped batches, and FLOP/s against this
CPU's fp32 matmul peak.

    python benchmarks/bench_train.py [--steps 12] [--hidden-size 128 --num-layers 4 ...] [--threads 2]

Both runs train the same scratch model on the same conversations (paper texts of 300-1500 tokens) through
`pipeline.finetune.finetune`; only ``packing`` differs. Padded: random batches padded to the longest with an
attention mask. Packed: length-grouped batches, right-padded, no mask (SDPA's causal kernel). tokens/s counts
real tokens. Achieved FLOP/s counts useful work only (6N per token plus causal attention, padding excluded),
so it is comparable with the matmul peak. The peak is measured before and after, because this machine is
shared and its speed moves.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time

import torch
import transformers

from pipeline.chat import WORD_LEVEL_FORMAT, encode_conversation
from pipeline.finetune import TrainSettings, finetune
from pipeline.generate import generate_worlds
from pipeline.modeling import build_scratch_model, count_parameters, training_flops
from pipeline.texts import conversation
from pipeline.tokenizer import build_word_tokenizer


def matmul_peak(threads: int, size: int = 1024, seconds: float = 2.0) -> float:
    """Best fp32 GFLOP/s of square matmuls over a few timed rounds on ``threads`` threads."""
    torch.set_num_threads(threads)
    a, b = torch.randn(size, size), torch.randn(size, size)
    for _ in range(3):
        a @ b
    best = 0.0
    for _ in range(5):
        n, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds / 5:
            torch.matmul(a, b)
            n += 1
        best = max(best, 2 * size**3 * n / (time.perf_counter() - start) / 1e9)
    return best


def bench_conversations(n: int, low: int, high: int, seed: int) -> list[list[dict]]:
    """``n`` FWD marking-deadend conversations (optimal setting) whose word-level length is in [low, high]."""
    worlds = generate_worlds(3 * n, seed)
    texts = [conversation(w, "fwd", "marking-deadend", "optimal") for w in worlds]
    tokenizer = build_word_tokenizer(t["value"] for c in texts for t in c)
    kept = [c for c in texts if low <= len(encode_conversation(tokenizer, WORD_LEVEL_FORMAT, c)[0]) <= high]
    if len(kept) < n:
        raise SystemExit(f"only {len(kept)} conversations of {low}-{high} tokens among {len(texts)}")
    return kept[:n]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--conversations", type=int, default=300)
    parser.add_argument("--min-tokens", type=int, default=300)
    parser.add_argument("--max-tokens", type=int, default=1500)
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--batch-size", type=int, default=16, help="sequences per step")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--hidden-size", type=int, default=128)
    parser.add_argument("--num-layers", type=int, default=4)
    parser.add_argument("--num-heads", type=int, default=4)
    parser.add_argument("--intermediate-size", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", choices=("padded", "packed"), help="run one of the two")
    args = parser.parse_args()
    transformers.logging.set_verbosity_error()

    conversations = bench_conversations(args.conversations, args.min_tokens, args.max_tokens, args.seed)
    tokenizer = build_word_tokenizer(t["value"] for c in conversations for t in c)
    lengths = [len(encode_conversation(tokenizer, WORD_LEVEL_FORMAT, c)[0]) for c in conversations]
    model_kwargs = dict(hidden_size=args.hidden_size, num_layers=args.num_layers, num_heads=args.num_heads,
                        intermediate_size=args.intermediate_size, max_length=max(lengths), seed=args.seed)
    probe = build_scratch_model(tokenizer, **model_kwargs)
    flops_per_real_token = training_flops(probe, lengths) / sum(lengths)
    print(f"cpu: {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}; torch {torch.__version__}, "
          f"{args.threads} threads")
    print(f"data: {len(conversations)} conversations, tokens min {min(lengths)} median "
          f"{statistics.median(lengths):.0f} max {max(lengths)}; vocab {len(tokenizer)}")
    print(f"model: {count_parameters(probe) / 1e6:.3f}M parameters, "
          f"{flops_per_real_token / 1e6:.2f} MFLOP per real token (training)")

    peaks = [matmul_peak(args.threads)]
    print(f"fp32 matmul peak: {peaks[0]:.1f} GFLOP/s")
    results = {}
    for name in ("padded", "packed"):
        if args.only and name != args.only:
            continue
        settings = TrainSettings(
            max_steps=args.steps, per_device_batch_size=args.batch_size, packing=name == "packed",
            max_length=max(lengths), report_to=(), logging_steps=args.steps, save_steps=10 * args.steps,
            torch_threads=args.threads, seed=args.seed,
        )
        with tempfile.TemporaryDirectory() as out:
            model = build_scratch_model(tokenizer, **model_kwargs)
            result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, settings, out)
        results[name] = result
        gflops = result.tokens_per_second * flops_per_real_token / 1e9
        print(f"{name:>6}: {result.tokens_per_second:8.0f} real tokens/s, real-token fraction "
              f"{result.real_token_fraction:.3f}, {gflops:.1f} GFLOP/s useful ({result.train_seconds:.1f} s "
              f"for {result.global_step} steps)")
    peaks.append(matmul_peak(args.threads))
    peak = max(peaks)
    print(f"fp32 matmul peak after: {peaks[1]:.1f} GFLOP/s; using the best, {peak:.1f}")
    if len(results) == 2:
        ratio = results["packed"].tokens_per_second / results["padded"].tokens_per_second
        print(f"packed / padded tokens/s: {ratio:.2f}x")
    for name, result in results.items():
        gflops = result.tokens_per_second * flops_per_real_token / 1e9
        print(f"{name}: {100 * gflops / peak:.0f}% of peak")


if __name__ == "__main__":
    main()
