"""Hydra's submitit launcher (the SLURM path's pickling, job folders and result collection), run here through its
local executor: `hydra/launcher=local_submitit`."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
import mlflow
import pytest

from pipeline.workflow.tracking import HASH_TAG, JOB_KIND, KIND_TAG, REPORT_KIND, STEP_KIND, STEP_TAG, step_run_tag

STEPS = ("data-build", "finetune", "eval")

pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="pip install '.[test]' (hydra-submitit-launcher)")

# Toy scale, and one job's steps for both: none texts do not depend on the direction, so the two jobs, started at
# once in two processes, race for the same data-build, finetune and eval.
TOY = ["data=toy", "model=toy", "train=toy", "eval=toy", "variant=none", "train.max_steps=2", "eval.n_worlds=3",
       "eval.max_new_tokens=32"]


@pytest.mark.slow
def test_a_sweep_through_the_submitit_launcher_runs_each_job_once_and_builds_the_report(tmp_path):
    command = [sys.executable, "-m", "pipeline.run", "-m", f"tracking.root={tmp_path}",
               "hydra/launcher=local_submitit", "hydra.launcher.timeout_min=5", "threads=1", *TOY, "direction=fwd,bwd"]
    # The jobs inherit the parent's environment (SLURM's sbatch exports it too): a run id left there must not make
    # them resume that run.
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MLFLOW_RUN_ID": "0" * 32}
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]

    # submitit's job folders: one per job, each with its pickles and its output (the job prints there, not to us).
    (sweep,) = (tmp_path / "multirun").iterdir()
    folders = [f for f in (sweep / ".submitit").iterdir() if f.name != "%j"]
    assert len(folders) == 2
    for folder in folders:
        names = {p.name for p in folder.iterdir()}
        assert {f"{folder.name}_submitted.pkl", f"{folder.name}_0_result.pkl", f"{folder.name}_0_log.out"} <= names
    logs = [(f / f"{f.name}_0_log.out").read_text() + (f / f"{f.name}_0_log.err").read_text() for f in folders]
    summaries = [line for log in logs for line in log.splitlines() if line.startswith("[job]")]
    assert len(summaries) == 2 and all("Traceback" not in log for log in logs), "\n".join(logs)[-4000:]
    assert sorted(line.split(" | ")[1] for line in summaries) == [
        "reused: data-build, finetune, eval", "reused: nothing"]

    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    experiment_id = client.get_experiment_by_name("cogmap").experiment_id

    def runs(kind):
        return client.search_runs([experiment_id], f"tags.`{KIND_TAG}` = '{kind}'")

    jobs = runs(JOB_KIND)
    assert sorted((r.data.tags["direction"], r.info.status) for r in jobs) == [("bwd", "FINISHED"), ("fwd", "FINISHED")]
    # Nothing twice: one step run per step, all finished, no two with one hash; both jobs point at them.
    steps = runs(STEP_KIND)
    assert sorted(r.data.tags[STEP_TAG] for r in steps) == sorted(STEPS)
    assert all(r.info.status == "FINISHED" for r in steps)
    assert max(Counter(r.data.tags[HASH_TAG] for r in steps).values()) == 1
    assert {tuple(r.data.tags[step_run_tag(s)] for s in STEPS) for r in jobs} == {
        tuple(next(r.info.run_id for r in steps if r.data.tags[STEP_TAG] == s) for s in STEPS)}

    # The parent ran the report callback when the jobs were collected.
    assert (tmp_path / "report" / "report.md").is_file()
    assert [r.info.status for r in runs(REPORT_KIND)] == ["FINISHED"]


@pytest.mark.slow
def test_a_preempted_job_is_requeued_by_submitit_and_resumes(tmp_path):
    """SLURM preempts with SIGTERM, then submitit's signal (USR2), on which submitit requeues the job: the job must
    leave SIGTERM to submitit (which ignores it) rather than end on it. Here the local executor stands in."""
    command = [sys.executable, "-m", "pipeline.run", "-m", f"tracking.root={tmp_path}",
               "hydra/launcher=local_submitit", "hydra.launcher.timeout_min=5", "threads=1", *TOY,
               "train.max_steps=800", "train.save_steps=100", "direction=fwd"]
    log = open(tmp_path / "sweep.log", "w")
    sweep = subprocess.Popen(command, cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT,
                             env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        deadline = time.monotonic() + 300
        while not list((tmp_path / "work" / "finetune").glob("*/checkpoints/checkpoint-100")):
            assert sweep.poll() is None and time.monotonic() < deadline, (tmp_path / "sweep.log").read_text()[-3000:]
            time.sleep(0.05)
        (folder,) = [f for f in next((tmp_path / "multirun").iterdir()).joinpath(".submitit").iterdir()
                     if f.name != "%j"]
        # The job's folder is named after the local controller's pid; the job runs in its child.
        (task,) = subprocess.run(["pgrep", "-P", folder.name], capture_output=True, text=True).stdout.split()
        os.kill(int(task), signal.SIGTERM)
        time.sleep(2)  # long enough for a job that ended on SIGTERM to be gone before the next signal
        os.kill(int(task), signal.SIGUSR2)
        assert sweep.wait(timeout=300) == 0, (tmp_path / "sweep.log").read_text()[-3000:]
    finally:
        if sweep.poll() is None:
            sweep.kill()
    output = (folder / f"{folder.name}_0_log.out").read_text()
    assert "Bypassing signal SIGTERM" in output and "Requeued job" in output
    assert "resuming from" in output and output.count("[job] ") == 1

    client = mlflow.MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    runs = client.search_runs([client.get_experiment_by_name("cogmap").experiment_id])
    finetunes = sorted(r.info.status for r in runs if r.data.tags.get(STEP_TAG) == "finetune")
    assert finetunes == ["FAILED", "FINISHED"]  # the preempted attempt, then the requeued one
    assert "RUNNING" not in {r.info.status for r in runs}
