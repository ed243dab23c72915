"""Run the GPU paths once on a CUDA machine and print what ran, how fast, and what it scored.

    python benchmarks/gpu_paths.py OUT_DIR [--work DIR] [--budget 540] [--only NAME ...] [--skip NAME ...]

Checks, in order (each a subprocess with its own time limit, all inside ``--budget`` seconds):

- ``env``: the GPU, the library versions, bf16 support.
- ``job-llama3``: the paper-scale path (``model=llama3_8b train=paper``) at a size that runs in a minute, first
  because it has never run on a GPU: a local ~100M-parameter Llama over Meta-Llama-3-8B's real tokenizer
  (``tests/fixtures/llama3_tokenizer``: 128,256 tokens, no pad token), the paper's template
  (``model/chat_format=paper``) and recipe (``train=paper``: bf16, tf32, gradient checkpointing, no packing,
  truncation at the context, FSDP through ``accelerate launch`` on the GPUs present), then decoded.
- ``job-default``: `python -m pipeline.run` as it is (the CPU default job), on the GPU: bf16 training,
  batched KV-cache decoding.
- ``job-hf-bf16``: a pretrained-model job (``model=hf``) on a local ~30M-parameter Llama with its own
  tokenizer, loaded in bfloat16 and fine-tuned a few bf16 steps, then decoded (the paper-scale code path
  at a size that runs in a minute).
- ``job-fsdp``: the same model through ``train.accelerate_config``: the finetune step runs
  ``accelerate launch`` with ``conf/accelerate/fsdp8.yaml`` rewritten for the GPUs present (FSDP2, full
  sharding, activation checkpointing, bf16 mixed precision); eval loads the saved full weights.
- ``fsdp-resume``: the FSDP job interrupted (SIGTERM to its process group) once its step-50 checkpoint is
  complete, then run again with the same command: it must resume from that sharded checkpoint and finish.
- ``vllm``: whether vLLM imports; if it does, the same model through ``eval.backend=vllm``.
- ``tests``: the test suite, with the GPU visible (pytest-xdist if installed).
- ``bench-train`` / ``bench-decode``: the two benchmarks on the GPU.

All jobs share one MLflow store under ``--work``; the log of every check goes to ``OUT_DIR/gpu_paths.log``
and a summary (status, seconds, and the finetune and eval metrics of every job) to ``OUT_DIR/summary.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

from pipeline.lm.chat import WORD_LEVEL_FORMAT

ROOT = Path(__file__).resolve().parents[1]
CHECKS = ("env", "job-llama3", "job-default", "job-hf-bf16", "job-fsdp", "fsdp-resume", "vllm", "tests",
          "bench-train", "bench-decode")
LLAMA3_TOKENIZER = ROOT / "tests" / "fixtures" / "llama3_tokenizer"
# The word-level chat format for the local model's own tokenizer, as Hydra overrides.
WORD_CHAT = [f"model.chat_format.{key}='{value}'" for key, value in asdict(WORD_LEVEL_FORMAT).items() if value is not None]
ENV_SCRIPT = """
import torch, transformers, accelerate, mlflow, hydra
print("torch", torch.__version__, "cuda", torch.version.cuda, "| transformers", transformers.__version__,
      "| accelerate", accelerate.__version__, "| mlflow", mlflow.__version__, "| hydra", hydra.__version__)
print("gpus:", [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())],
      "bf16:", torch.cuda.is_available() and torch.cuda.is_bf16_supported())
"""


def make_local_model(target: Path, hidden: int = 512, layers: int = 8, heads: int = 8,
                     tokenizer_dir: Path | None = None) -> Path:
    """A saved Llama (safetensors, with a word-level tokenizer or the one in ``tokenizer_dir``) standing in
    for a downloaded base model."""
    from transformers import AutoTokenizer

    from pipeline.core.generators import GeneratorConfig, generate_worlds
    from pipeline.lm.model_settings import ModelSettings
    from pipeline.lm.models import make_model
    from pipeline.core.texts import MAP_VARIANTS, conversation
    from pipeline.lm.tokenizer import build_word_tokenizer

    if tokenizer_dir is not None:
        tokenizer = AutoTokenizer.from_pretrained(tokenizer_dir, local_files_only=True)
    else:
        worlds = generate_worlds(64, seed="gpu-paths", cfg=GeneratorConfig(size_x=(2, 6), size_y=(2, 6)))
        texts = [turn["value"] for world in worlds for direction in ("fwd", "bwd") for variant in MAP_VARIANTS
                 for mode in ("optimal", "reachable") for turn in conversation(world, direction, variant, mode, prompt="paper")]
        tokenizer = build_word_tokenizer(texts)
    settings = ModelSettings(hidden_size=hidden, num_layers=layers, num_heads=heads, intermediate_size=4 * hidden,
                             max_length=8192 if tokenizer_dir else 2048)
    model = make_model(settings, tokenizer)
    model.save_pretrained(target)
    tokenizer.save_pretrained(target)
    return target


def fsdp_config(target: Path, processes: int) -> Path:
    """conf/accelerate/fsdp8.yaml with num_processes set to the GPUs present."""
    text = (ROOT / "conf" / "accelerate" / "fsdp8.yaml").read_text()
    target.write_text(text.replace("num_processes: 8", f"num_processes: {processes}"))
    return target


class Runner:
    """Runs checks inside a total time budget, appending every output to one log."""

    def __init__(self, out: Path, budget: float):
        self.log = (out / "gpu_paths.log").open("a")
        self.deadline = time.monotonic() + budget
        self.results: dict[str, dict] = {}
        self.output = ""  # the last check's output

    def run(self, name: str, command: list[str], limit: float, env: dict | None = None) -> bool:
        left = self.deadline - time.monotonic()
        if left < 30:
            self.results[name] = {"status": "skipped (budget)"}
            print(f"=== {name}: skipped, {left:.0f} s of the budget left", flush=True)
            return False
        limit = min(limit, left - 10)
        print(f"=== {name}: {' '.join(command)} (limit {limit:.0f} s)", flush=True)
        self.log.write(f"\n=== {name}: {' '.join(command)}\n")
        self.log.flush()
        started = time.monotonic()
        try:
            proc = subprocess.run(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                  timeout=limit, env={**os.environ, **(env or {})})
            output, status = proc.stdout, "ok" if proc.returncode == 0 else f"failed (rc {proc.returncode})"
        except subprocess.TimeoutExpired as timeout:
            output = timeout.stdout.decode() if isinstance(timeout.stdout, bytes) else (timeout.stdout or "")
            status = f"timed out after {limit:.0f} s"
        seconds = time.monotonic() - started
        self.output = output
        self.log.write(output)
        self.log.flush()
        tail = output.strip().splitlines()[-12:]
        print("\n".join("    " + line for line in tail))
        print(f"=== {name}: {status} in {seconds:.1f} s", flush=True)
        self.results[name] = {"status": status, "seconds": round(seconds, 1)}
        return status == "ok"

    def interrupt(self, name: str, command: list[str], marker: str, root: Path, limit: float) -> bool:
        """Run ``command`` in its own process group and SIGTERM the group once a file matching the glob
        ``marker`` exists under ``root``; True if it was interrupted that way."""
        print(f"=== {name}: {' '.join(command)} (interrupted at {marker})", flush=True)
        self.log.write(f"\n=== {name}: {' '.join(command)}\n")
        self.log.flush()
        started, deadline = time.monotonic(), min(time.monotonic() + limit, self.deadline - 10)
        proc = subprocess.Popen(command, cwd=ROOT, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        seen = False
        while proc.poll() is None and time.monotonic() < deadline and not seen:
            seen = any(root.glob(marker))
            time.sleep(0.5)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        status = "interrupted after the marker" if seen else f"no marker (rc {proc.returncode})"
        print(f"=== {name}: {status} in {time.monotonic() - started:.1f} s", flush=True)
        self.results[name] = {"status": status, "seconds": round(time.monotonic() - started, 1)}
        return seen


def job_metrics(uri: str) -> list[dict]:
    """Every job of the store with its finetune and eval metrics (the figures worth reading)."""
    import mlflow

    client = mlflow.tracking.MlflowClient(uri)
    keep = ("tokens_per_second", "train_seconds", "final_loss", "token_accuracy", "real_token_fraction",
            "global_step", "success_rate", "success_rate_interp", "success_rate_extrap", "rate_parsed",
            "rate_map_exact", "n_episodes", "eval_seconds")
    jobs = []
    for experiment in client.search_experiments():
        for run in client.search_runs([experiment.experiment_id], "tags.`cogmap.kind` = 'job'"):
            row = {"job": run.info.run_name, "status": run.info.status}
            for step in ("finetune", "eval"):
                step_id = run.data.tags.get(f"cogmap.run.{step}")
                if step_id:
                    step_run = client.get_run(step_id)
                    row[step] = {k: v for k, v in step_run.data.metrics.items() if k in keep}
                    row[step]["wall_s"] = round(((step_run.info.end_time or 0) - step_run.info.start_time) / 1000, 1)
                    row[step]["parameters"] = step_run.data.params.get("model.parameters")
            jobs.append(row)
    return jobs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="where gpu_paths.log and summary.json go")
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "gpu_paths", help="store, models, scratch")
    parser.add_argument("--budget", type=float, default=540, help="seconds for all checks together")
    parser.add_argument("--only", action="append", choices=CHECKS)
    parser.add_argument("--skip", action="append", choices=CHECKS, default=[])
    parser.add_argument("--hf-steps", type=int, default=100)
    parser.add_argument("--toy", action="store_true", help="toy data and a few steps (checks this script on a CPU)")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    args.work.mkdir(parents=True, exist_ok=True)
    wanted = [c for c in CHECKS if (not args.only or c in args.only) and c not in args.skip]
    runner, python = Runner(args.out, args.budget), sys.executable
    root = args.work / "store"
    store = [f"tracking.root={root}"]
    if args.toy:
        store += ["data=toy", "train.max_steps=4", "train.save_steps=4", "eval.n_worlds=4", "eval.max_new_tokens=64"]
    gpus = int(subprocess.run([python, "-c", "import torch; print(torch.cuda.device_count())"],
                              capture_output=True, text=True).stdout.strip() or 0)
    hf_job = ["model=hf", f"model.path={args.work / 'local-llama'}", "model.max_length=2048",
              f"train.max_steps={args.hf_steps}", "train.learning_rate=3e-4", "train.save_steps=1000",
              "eval.n_worlds=64", "eval.max_new_tokens=512",
              "train.torch_compile=none",  # as first measured; compiled layers under FSDP2 have not run yet
              *WORD_CHAT, *store]  # --toy's overrides come last

    fsdp = f"train.accelerate_config={fsdp_config(args.work / f'fsdp{gpus}.yaml', max(gpus, 1))}"
    if "env" in wanted:
        runner.run("env", ["nvidia-smi"], 30)
        runner.run("env-python", [python, "-c", ENV_SCRIPT], 60)
    if "job-llama3" in wanted:
        llama3 = args.work / "local-llama3"
        if not llama3.is_dir():
            make_local_model(llama3, *((64, 2, 2) if args.toy else ()), tokenizer_dir=LLAMA3_TOKENIZER)
        runner.run("job-llama3", [python, "-m", "pipeline.run", "model=hf", f"model.path={llama3}", "model.dtype=bfloat16",
                                  "model/chat_format=paper", "train=paper", fsdp, f"train.max_steps={args.hf_steps}",
                                  "train.save_steps=1000", "eval.n_worlds=64", "eval.max_new_tokens=512", *store], 300)
    if "job-default" in wanted:
        runner.run("job-default", [python, "-m", "pipeline.run", *store], 300)
    if {"job-hf-bf16", "job-fsdp", "fsdp-resume", "vllm"} & set(wanted) and not (args.work / "local-llama").is_dir():
        make_local_model(args.work / "local-llama", *((64, 2, 2) if args.toy else ()))
    if "job-hf-bf16" in wanted:
        runner.run("job-hf-bf16", [python, "-m", "pipeline.run", *hf_job, "model.dtype=bfloat16"], 240)
    if "job-fsdp" in wanted:
        runner.run("job-fsdp", [python, "-m", "pipeline.run", *hf_job, fsdp], 240)
    if "fsdp-resume" in wanted:
        resume_root = args.work / "resume"
        command = [python, "-m", "pipeline.run", *hf_job, fsdp, "train.max_steps=100", "train.save_steps=50",
                   f"tracking.root={resume_root}"]
        marker = "work/finetune/*/checkpoints/checkpoint-50/trainer_state.json"
        if runner.interrupt("fsdp-resume-1", command, marker, resume_root, 240):
            runner.run("fsdp-resume-2", command, 240)
            runner.results["fsdp-resume-2"]["resumed"] = "resuming from" in runner.output
    if "vllm" in wanted and runner.run("vllm", [python, "-c", "import vllm; print('vllm', vllm.__version__)"], 60):
        runner.run("job-vllm", [python, "-m", "pipeline.run", *hf_job, "model.dtype=bfloat16", "eval.backend=vllm"], 240)
    if "tests" in wanted:
        xdist = subprocess.run([python, "-c", "import xdist"], capture_output=True).returncode == 0
        runner.run("tests", [python, "-m", "pytest", "-q", *(["-n", "auto"] if xdist else []), "tests"], 420)
    if "bench-train" in wanted:
        runner.run("bench-train", [python, "benchmarks/bench_train.py", "--steps", "100"], 180)
    if "bench-decode" in wanted:
        runner.run("bench-decode", [python, "benchmarks/bench_decode.py"], 180)

    summary = {"checks": runner.results}
    if (root / "mlflow.db").is_file():
        summary["jobs"] = job_metrics(f"sqlite:///{root / 'mlflow.db'}")
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
