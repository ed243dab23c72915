"""What the end-to-end workflow tests share: the toy job's overrides, and helpers that run jobs (in-process
or as the README's command line), kill them, and read the store back."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import pytest
from conftest import compose_job

from pipeline.workflow.tracking import (
    EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, STEP_KIND, STEP_TAG, step_run_tag,
)

TOY = ["data=toy", "model=toy", "train=toy", "eval=toy"]
# Small enough to be quick, big enough to kill in the middle: 8 optimizer steps with a checkpoint every 4,
# and reachable episodes recorded one by one, two at a time.
# The paper's longer prompt keeps a step slow enough that the kill lands before the next logged step.
KILLABLE = [*TOY, "model.prompt=paper", "mode=reachable", "variant=no-all", "train.max_steps=8", "train.save_steps=4",
            "train.logging_steps=2", "eval.batch_size=2", "eval.max_new_tokens=48", "eval.max_moves=4",
            "hydra/job_logging=none"]
EXAMPLE_WORLD = {"question": {"world_size_x": 4, "world_size_y": 3, "wall": [[1, 1], [2, 2]], "pit": [[3, 0]],
                              "start": [0, 0], "goal": [3, 2], "gridstart_x": 0, "gridstart_y": 0}}


def toy_config(root, *overrides):
    return compose_job(root, *TOY, *overrides)


def cli_command(root, *overrides, multirun=False):
    return [sys.executable, "-m", "pipeline.run", *(["-m"] if multirun else []), f"tracking.root={root}", *overrides]


def run_cli(root, *overrides, multirun=False, timeout=900):
    return subprocess.run(cli_command(root, *overrides, multirun=multirun), cwd=root, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def store_runs(root, kind=None, experiment="cogmap"):
    mlflow.set_tracking_uri(f"sqlite:///{root}/mlflow.db")
    query = f"tags.`{KIND_TAG}` = '{kind}'" if kind else ""
    return mlflow.search_runs(experiment_names=[experiment], filter_string=query, output_format="list",
                              order_by=["attributes.start_time ASC"])


def step_runs(root, step):
    return [r for r in store_runs(root, STEP_KIND) if r.data.tags[STEP_TAG] == step]


def eval_metrics(root):
    (job,) = [r for r in store_runs(root, JOB_KIND) if r.info.status == "FINISHED"]
    run = mlflow.get_run(job.data.tags[step_run_tag("eval")])
    return {k: v for k, v in run.data.metrics.items() if k != "step_seconds"}, run


def read_episodes(run):  # from the store last searched
    path = mlflow.artifacts.download_artifacts(run_id=run.info.run_id, artifact_path=EPISODES_ARTIFACT)
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def kill_when(root, overrides, ready, what, timeout=600):
    """Start the job, wait until ``ready()`` holds, kill -9 it; fail if it ends first."""
    log = open(root / f"killed-{what}.log", "w")
    process = subprocess.Popen(cli_command(root, *overrides), cwd=root, stdout=log, stderr=subprocess.STDOUT,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    deadline = time.monotonic() + timeout
    try:
        while not ready():
            if process.poll() is not None:
                pytest.fail(f"the job ended (rc {process.returncode}) before {what}:\n"
                            + (root / f"killed-{what}.log").read_text()[-3000:])
            if time.monotonic() > deadline:
                pytest.fail(f"no {what} within {timeout} s")
            time.sleep(0.05)
        os.kill(process.pid, signal.SIGKILL)
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        log.close()
    assert process.returncode == -signal.SIGKILL


def complete_checkpoints(root):
    return sorted(root.glob("work/finetune/*/checkpoints/checkpoint-*/trainer_state.json"))


def partial_lines(root):
    files = list(root.glob("work/eval/*/episodes.partial.jsonl"))
    return files[0].read_text().splitlines() if files else []


def loss_curve(run_id):
    history = mlflow.MlflowClient().get_metric_history(run_id, "loss")  # in the store last searched
    return {m.step: m.value for m in history}
