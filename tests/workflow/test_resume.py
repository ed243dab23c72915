"""Kill and resume, end to end: kill -9 during finetune and during eval, rerun the same command: finished
steps are reused, training resumes from its last checkpoint (the loss curve continues where it stopped, value
for value), eval resumes from its finished episodes, and the final records and metrics equal an uninterrupted
run's; the interrupted runs end KILLED in MLflow. Torn checkpoints and partial files, vanished artifacts, and
two parallel workers on a fresh store (every run there, no step twice)."""

from __future__ import annotations

import json
from pathlib import Path

import mlflow
import pytest

from pipeline.workflow.evaluation import PartialRecords
from pipeline.workflow.finetune import discard_incomplete_checkpoints
from pipeline.workflow.steps import ARTIFACTS_TAG, get_or_run
from pipeline.workflow.tracking import (
    JOB_KIND, STEP_KIND, STEP_TAG, ensure_experiment, step_run_tag,
)
from jobs import KILLABLE, TOY, complete_checkpoints, eval_metrics, kill_when, loss_curve, partial_lines, read_episodes, run_cli, step_runs, store_runs



@pytest.mark.slow
def test_kill_9_during_finetune_and_eval_then_rerun_equals_an_uninterrupted_run(tmp_path):
    reference, killed = tmp_path / "reference", tmp_path / "killed"
    reference.mkdir(), killed.mkdir()
    done = run_cli(reference, *KILLABLE)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    expected, expected_eval = eval_metrics(reference)
    expected_episodes = read_episodes(expected_eval)
    (reference_finetune,) = step_runs(reference, "finetune")
    reference_curve = loss_curve(reference_finetune.info.run_id)
    assert sorted(reference_curve) == [2, 4, 6, 8]

    # 1st attempt: killed during finetune, once a checkpoint is complete (trainer_state.json comes last).
    kill_when(killed, KILLABLE, lambda: complete_checkpoints(killed), "a checkpoint")
    # The last complete checkpoint when the kill landed (the trainer may have gone a step or two past it).
    resumed_at = max(int(path.parent.name.split("-")[-1]) for path in complete_checkpoints(killed))
    assert resumed_at < 8, "the kill landed after the last checkpoint: nothing left to resume"
    (data_run,) = step_runs(killed, "data-build")
    (first_finetune,) = step_runs(killed, "finetune")
    assert data_run.info.status == "FINISHED" and first_finetune.info.status == "RUNNING"  # as the kill left it

    # 2nd attempt: reuses data-build, resumes training, then is killed during eval with episodes recorded.
    kill_when(killed, KILLABLE, lambda: len(partial_lines(killed)) >= 2, "recorded episodes")
    before_rerun = partial_lines(killed)
    assert 2 <= len(before_rerun) < 8
    finetunes = step_runs(killed, "finetune")
    assert [r.info.status for r in finetunes] == ["KILLED", "FINISHED"]
    assert len(step_runs(killed, "data-build")) == 1
    # Resumed, not restarted: the loss curve goes on after the checkpoint, equal value for value. (The killed run
    # may have logged a step past its last checkpoint before the kill landed; the resumed run redoes it.)
    first, second = (loss_curve(run.info.run_id) for run in finetunes)
    assert first == {step: reference_curve[step] for step in first} and set(first) >= {s for s in (2, 4) if s <= resumed_at}
    assert second == {step: reference_curve[step] for step in reference_curve if step > resumed_at}
    resumed_log = (killed / "killed-recorded episodes.log").read_text()
    assert "There were missing keys" not in resumed_log  # the tied head is stored once: not an alarm

    # 3rd attempt: finishes, reusing data-build and finetune and the episodes already recorded.
    done = run_cli(killed, *KILLABLE)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "reused: data-build, finetune" in done.stdout
    after = partial_lines(killed)
    assert after[: len(before_rerun)] == before_rerun  # kept, not redone
    assert len(after) == 8 and len({json.loads(line)["world_index"] for line in after}) == 8

    metrics, eval_run = eval_metrics(killed)
    assert metrics == expected
    assert read_episodes(eval_run) == expected_episodes
    assert [r.info.status for r in step_runs(killed, "eval")] == ["KILLED", "FINISHED"]
    statuses = [r.info.status for r in store_runs(killed, JOB_KIND)]
    assert statuses == ["KILLED", "KILLED", "FINISHED"]  # never left RUNNING, never looking finished
    assert all(r.info.status in ("FINISHED", "KILLED") for r in store_runs(killed))


def test_a_torn_checkpoint_is_discarded_before_resuming(tmp_path):
    checkpoints = tmp_path / "checkpoints"
    for step, complete in ((4, True), (8, False)):
        folder = checkpoints / f"checkpoint-{step}"
        folder.mkdir(parents=True)
        (folder / "model.safetensors").write_bytes(b"weights")
        if complete:
            (folder / "trainer_state.json").write_text(json.dumps({"global_step": step}))
    (checkpoints / "checkpoint-12").mkdir()
    (checkpoints / "checkpoint-12" / "trainer_state.json").write_text('{"global_st')  # killed mid-write
    removed = discard_incomplete_checkpoints(tmp_path)
    assert sorted(p.name for p in removed) == ["checkpoint-12", "checkpoint-8"]
    assert sorted(p.name for p in checkpoints.iterdir()) == ["checkpoint-4"]


def test_a_torn_partial_eval_file_resumes_without_gluing_records(tmp_path):
    path = tmp_path / "episodes.partial.jsonl"
    path.write_text(json.dumps({"world_index": 0, "success": True}) + "\n" + '{"world_index": 1, "succ')
    partial = PartialRecords(path)
    assert set(partial.records) == {0}
    partial.add({"world_index": 1, "success": False})
    partial.close()
    assert set(PartialRecords(path).records) == {0, 1}


def test_a_finished_step_whose_artifacts_vanished_runs_again(tmp_path):
    experiment_id = ensure_experiment(f"sqlite:///{tmp_path}/mlflow.db", "steps", str(tmp_path / "artifacts"))
    mlflow.set_experiment(experiment_id=experiment_id)

    def body(step_dir):
        (step_dir / "out.txt").write_text("made")
        mlflow.log_artifact(str(step_dir / "out.txt"))

    def run():
        with mlflow.start_run(run_name="job"):
            return get_or_run("data-build", "h1", experiment_id=experiment_id, work_dir=tmp_path / "work", tags={},
                              body=body)

    first = run()
    assert mlflow.get_run(first.run_id).data.tags[ARTIFACTS_TAG] == "1"
    for file in (tmp_path / "artifacts").rglob("out.txt"):
        file.unlink()  # someone cleaned the artifact store
    second = run()
    assert not second.reused and second.run_id != first.run_id
    assert Path(second.artifact("out.txt")).read_text() == "made"
    assert run().run_id == second.run_id  # and the rebuilt one is reused from then on


@pytest.mark.slow
def test_two_parallel_workers_on_a_fresh_store_run_every_job_once(tmp_path):
    # none texts do not depend on the direction: both jobs need the same data-build and finetune, at once.
    done = run_cli(tmp_path, "hydra/launcher=local2", "threads=1", *TOY, "variant=none", "direction=fwd,bwd",
                    "train.max_steps=2", "eval.n_worlds=3", "eval.max_new_tokens=32", multirun=True)
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-4000:]
    assert "Traceback" not in output and "Error executing job" not in output
    jobs = store_runs(tmp_path, JOB_KIND)
    assert len(jobs) == 2 and all(r.info.status == "FINISHED" for r in jobs)
    assert {r.data.tags["direction"] for r in jobs} == {"fwd", "bwd"}
    steps = store_runs(tmp_path, STEP_KIND)
    assert all(r.info.status == "FINISHED" for r in steps)
    # One run per step hash: the second worker waited on the lock and reused what the first made.
    assert sorted(r.data.tags[STEP_TAG] for r in steps) == ["data-build", "eval", "finetune"]
    assert len({r.data.tags[step_run_tag("finetune")] for r in jobs}) == 1
    assert sum("reused: data-build, finetune, eval" in line for line in done.stdout.splitlines()) == 1
    assert (tmp_path / "report" / "report.md").is_file()
