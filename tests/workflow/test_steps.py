"""Hashed steps: reuse of FINISHED runs, stale RUNNING runs marked KILLED, failures marked FAILED."""

import mlflow
import pytest

from pipeline.workflow.steps import find_finished, get_or_run
from pipeline.workflow.tracking import HASH_TAG, STEP_TAG, ensure_experiment


@pytest.fixture(scope="module")
def shared_store(tmp_path_factory):
    # A new SQLite store costs seconds of migrations: one per module, one experiment per test.
    root = tmp_path_factory.mktemp("store")
    return f"sqlite:///{root}/mlflow.db", root


@pytest.fixture
def store(shared_store, request):
    uri, root = shared_store
    experiment_id = ensure_experiment(uri, request.node.name, str(root / request.node.name))
    mlflow.set_experiment(experiment_id=experiment_id)
    yield experiment_id, root / request.node.name / "work"
    while mlflow.active_run():
        mlflow.end_run()


def _run(store, body, step_hash="abc"):
    experiment_id, work = store
    with mlflow.start_run(run_name="job"):
        return get_or_run("data-build", step_hash, experiment_id=experiment_id, work_dir=work, tags={"x": "1"}, body=body)


def test_a_finished_step_is_reused_and_a_new_hash_runs(store):
    calls = []

    def body(step_dir):
        calls.append(step_dir)
        (step_dir / "out.txt").write_text("hello")
        mlflow.log_artifact(str(step_dir / "out.txt"))

    first = _run(store, body)
    again = _run(store, body)
    other = _run(store, body, step_hash="def")
    assert (first.reused, again.reused, other.reused) == (False, True, False)
    assert again.run_id == first.run_id and len(calls) == 2
    assert open(again.artifact("out.txt")).read() == "hello"
    run = mlflow.get_run(first.run_id)
    assert run.data.tags[STEP_TAG] == "data-build" and run.data.tags[HASH_TAG] == "abc"
    assert run.data.tags["mlflow.parentRunId"]  # nested under the job that ran it


def test_a_failing_step_is_failed_and_not_reused(store):
    def boom(step_dir):
        raise RuntimeError("bad input")

    with pytest.raises(RuntimeError, match="bad input"):
        _run(store, boom)
    experiment_id, _ = store
    assert find_finished(experiment_id, "data-build", "abc") is None
    statuses = {r.info.status for r in mlflow.search_runs([experiment_id], output_format="list") if r.info.run_name == "data-build"}
    assert statuses == {"FAILED"}
    assert not _run(store, lambda d: None).reused


def test_a_run_left_running_by_a_dead_process_is_marked_killed(store):
    experiment_id, _ = store
    client = mlflow.MlflowClient()
    stale = client.create_run(experiment_id, tags={STEP_TAG: "data-build", HASH_TAG: "abc"}, run_name="data-build")
    done = _run(store, lambda d: None)
    assert client.get_run(stale.info.run_id).info.status == "KILLED"
    assert client.get_run(done.run_id).info.status == "FINISHED"


@pytest.mark.parametrize("damage", ["truncate", "delete", "edit"])
def test_a_finished_steps_damaged_artifact_is_detected_and_the_step_reruns(store, capsys, damage):
    """Each step records every artifact's SHA-256; a reuse checks them, so a file cut off mid-line, deleted or
    edited behind a FINISHED run makes the step run again (one line says why), and the new run is reused."""
    def body(step_dir):
        (step_dir / "episodes.jsonl").write_text('{"world_index": 0, "success": true}\n{"world_index": 1}\n')
        (step_dir / "other.txt").write_text("kept")
        mlflow.log_artifact(str(step_dir / "episodes.jsonl"))
        mlflow.log_artifact(str(step_dir / "other.txt"))

    first = _run(store, body, step_hash=f"h-{damage}")
    assert _run(store, body, step_hash=f"h-{damage}").reused
    (episodes,) = [p for p in (store[1].parent).rglob("episodes.jsonl") if first.run_id in str(p)]
    if damage == "truncate":
        episodes.write_bytes(episodes.read_bytes()[:30])
    elif damage == "delete":
        episodes.unlink()
    else:
        episodes.write_text(episodes.read_text().replace("true", "false"))
    capsys.readouterr()
    second = _run(store, body, step_hash=f"h-{damage}")
    assert not second.reused and second.run_id != first.run_id
    reason = "is missing" if damage == "delete" else "changed since the step finished"
    (line,) = [line for line in capsys.readouterr().out.splitlines() if line.startswith("[data-build]")]
    assert f"not reusing run {first.run_id}: its artifact episodes.jsonl {reason}" in line
    assert mlflow.get_run(first.run_id).data.tags["cogmap.note"].startswith("not reused: its artifact episodes.jsonl")
    again = _run(store, body, step_hash=f"h-{damage}")
    assert again.reused and again.run_id == second.run_id
