"""Determinism, end to end: the same config twice gives the same step hashes, dataset hash, records and metrics."""

from __future__ import annotations


import pytest

from pipeline.workflow.job import run_job
from jobs import read_episodes, step_runs, toy_config



@pytest.mark.slow
def test_the_same_config_twice_gives_identical_hashes_records_and_metrics(tmp_path):
    # model.max_length=58, the one context length: the NONE conversations of the smaller train worlds fit it
    # (54-69 tokens) and train, while the larger test worlds' prompts (47-63 tokens, task prompt) no longer fit,
    # so this also shows a too-large test world becoming a per-episode error while the job finishes.
    overrides = ["variant=none", "train.max_steps=2", "eval.max_new_tokens=32", "model.max_length=58"]
    results = []
    for name in ("a", "b"):
        root = tmp_path / name
        metrics = run_job(toy_config(root, *overrides))
        data = step_runs(root, "data-build")[0]
        (finetune,) = step_runs(root, "finetune")
        (evaluation,) = step_runs(root, "eval")
        results.append({
            "metrics": {k: v for k, v in metrics.items() if k != "step_seconds"},
            "hashes": [run.data.tags["cogmap.hash"] for run in (data, finetune, evaluation)],
            "dataset_sha256": data.data.tags["dataset_sha256"],
            "final_loss": finetune.data.metrics["final_loss"],
            "episodes": read_episodes(evaluation),
        })
    assert results[0] == results[1]
    episodes = results[0]["episodes"]
    errors = [r for r in episodes if r["outcome"] == "error"]
    assert errors and len(errors) < len(episodes)
    assert all("context of 58" in r["error"] and r["success"] is False for r in errors)
    assert results[0]["metrics"]["rate_error"] == len(errors) / len(episodes)
