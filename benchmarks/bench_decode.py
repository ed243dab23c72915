"""Decoding speed: cached multi-turn episodes vs the two baselines, and batched vs unbatched answers.

    .venv/bin/python benchmarks/bench_decode.py [--worlds 32] [--repeats 2] [--threads 2] [--device cuda]

One randomly initialised Llama (CPU default size: hidden 128, 4 layers, 2 heads, intermediate 512) and the
same generated worlds (sides 3-6) for every contender. An untrained model neither ends its turns nor
answers moves, so to get realistic multi-turn episodes the answers' lengths are forced by caps (first
answer: `--first-tokens`, standing in for a Thought; later answers: `--move-tokens`, a bare move) and the
move is a random free move picked from the answer text (`choose_move`). All contenders see exactly the
same token sequences (checked), so only the decoding strategy differs.
"""

from __future__ import annotations

import argparse
import time

import torch

from pipeline.lm.chat import WORD_LEVEL_FORMAT, encode_prompt, turn_end_ids
from pipeline.lm.decoding.hf import HFDecoder
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import make_model
from pipeline.core.generators import GeneratorConfig, generate_worlds
from pipeline.core.texts import conversation, prompt_turns
from pipeline.lm.tokenizer import build_word_tokenizer


def random_free_move(text: str, observation: str) -> str | None:
    """A free move of the observation, picked by the answer text (deterministic across strategies)."""
    lines = observation.split("Possible:\n")[-1].split("\n")
    moves = lines[1::2]
    return moves[sum(map(ord, text)) % len(moves)] if moves else None


def timed(fn, repeats: int):
    """(result, seconds): the best wall time of `repeats` runs (this box is shared; the best run is the
    one least disturbed by other jobs)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return result, best


def generate_batched(model, tokenizer, prompts, batch_size, max_new_tokens):
    """`model.generate` on left-padded batches sorted by length; returns the tokens generated."""
    stop = turn_end_ids(tokenizer, WORD_LEVEL_FORMAT)[0]
    encoded = sorted((encode_prompt(tokenizer, WORD_LEVEL_FORMAT, turns) for turns in prompts), key=len)
    n_tokens = 0
    for start in range(0, len(encoded), batch_size):
        batch = encoded[start:start + batch_size]
        width = max(map(len, batch))
        ids = torch.tensor([[tokenizer.pad_token_id] * (width - len(p)) + p for p in batch], device=model.device)
        mask = torch.tensor([[0] * (width - len(p)) + [1] * len(p) for p in batch], device=model.device)
        out = model.generate(ids, attention_mask=mask, do_sample=False, max_new_tokens=max_new_tokens,
                             eos_token_id=stop, pad_token_id=tokenizer.pad_token_id)[:, width:]
        for row in out.tolist():
            n_tokens += row.index(stop) + 1 if stop in row else len(row)
    return n_tokens


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", type=int, default=32)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--max-steps", type=int, default=20)
    parser.add_argument("--first-tokens", type=int, default=64)
    parser.add_argument("--move-tokens", type=int, default=2)
    parser.add_argument("--answer-tokens", type=int, default=128)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    worlds = generate_worlds(args.worlds, seed="bench-decode", cfg=GeneratorConfig(size_x=(3, 6), size_y=(3, 6)))
    texts = [t["value"] for w in worlds for t in conversation(w, "bwd", "marking-deadend", "reachable", prompt="paper")]
    tokenizer = build_word_tokenizer(texts)
    model = make_model(ModelSettings(max_length=4096), tokenizer).eval().to(args.device)  # the CPU default's model
    print(f"model: {sum(p.numel() for p in model.parameters()) / 1e6:.2f}M params on {args.device}, threads {args.threads}; "
          f"{len(worlds)} worlds, sides 3-6")

    def decoder(batch_size, **caps):
        return HFDecoder(model, tokenizer, WORD_LEVEL_FORMAT, batch_size=batch_size, **caps)

    # Reachable setting
    caps = dict(max_new_tokens=args.first_tokens, max_followup_tokens=args.move_tokens)
    play = dict(max_moves=args.max_steps, choose_move=random_free_move)
    dec = decoder(args.batch_size, **caps)
    dec.play(worlds[:2], **play)  # warm-up
    cached, t_cached = timed(lambda: dec.play(worlds, **play), args.repeats)
    reencoded, t_reencode = timed(lambda: dec.play(worlds, strategy="reencode", **play), args.repeats)
    one_by_one, t_generate = timed(lambda: dec.play(worlds, strategy="generate", **play), args.repeats)
    assert [r.answers for r in cached] == [r.answers for r in reencoded] == [r.answers for r in one_by_one]
    turns = sum(len(r.answers) for r in cached)
    print(f"\nreachable: {turns} turns, {turns / len(worlds):.1f} per episode; "
          f"{sum(r.n_tokens for r in cached)} tokens generated")
    print(f"  (best of {args.repeats} runs each)")
    rate = {"cached": len(worlds) / t_cached, "reencode": len(worlds) / t_reencode,
            "generate": len(worlds) / t_generate}
    for name, value in rate.items():
        print(f"  {name:<9} {value:7.2f} episodes/s")
    print(f"  cached / one-at-a-time generate: {rate['cached'] / rate['generate']:.1f}x (target >= 5x)")
    print(f"  cached / re-encoded history:     {rate['cached'] / rate['reencode']:.1f}x (target >= 2x)")

    # Optimal setting
    prompts = [prompt_turns(w, "paper") for w in worlds]
    ours = {}
    for batch_size in (args.batch_size, 1):
        dec = decoder(batch_size, max_new_tokens=args.answer_tokens)
        gens, seconds = timed(lambda: dec.generate(prompts), args.repeats)
        ours[batch_size] = sum(g.n_tokens for g in gens) / seconds
    n_gen, t_gen = timed(lambda: generate_batched(model, tokenizer, prompts, args.batch_size, args.answer_tokens),
                         args.repeats)
    print(f"\noptimal: {len(prompts)} answers capped at {args.answer_tokens} tokens")
    print(f"  ours, batch {args.batch_size:<3}       {ours[args.batch_size]:8.0f} tokens/s")
    print(f"  ours, batch 1            {ours[1]:8.0f} tokens/s  (batched {ours[args.batch_size] / ours[1]:.1f}x)")
    print(f"  model.generate, batch {args.batch_size:<3}{n_gen / t_gen:8.0f} tokens/s")


if __name__ == "__main__":
    main()
