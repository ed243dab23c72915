"""Reliability of a night-long sweep: faults, bad input, concurrency and determinism, end to end.

- kill -9 during finetune and during eval, rerun the same command: finished steps are reused, training
  resumes from its last checkpoint (the loss curve continues where it stopped, value for value), eval
  resumes from its finished episodes, and the final records and metrics equal an uninterrupted run's;
  the interrupted runs end up KILLED in MLflow, never FINISHED or RUNNING.
- two workers of the local parallel launcher on a fresh store: every run there, no error, no step twice.
- bad input (a dozen kinds): an early error naming the value and what is allowed, or a per-episode error
  record (a test world longer than the model's context); a sweep with a bad job keeps the others' results.
- determinism: the same config twice gives the same step hashes, dataset hash, records and metrics.
- safety: models load from safetensors only, remote code only on request, `mlflow ui` on 127.0.0.1.

Existing unit tests cover the pieces (config checks: test_config.py, model loading: test_modeling.py,
stale step runs: test_steps.py, the world schema: test_world.py); these tests drive whole jobs.
"""

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
from conftest import ROOT, compose_job

from pipeline.workflow.config import ConfigError
from pipeline.workflow.evaluation import PartialRecords
from pipeline.workflow.finetune import discard_incomplete_checkpoints
from pipeline.lm.models import ModelLoadError, ModelSettings
from pipeline.workflow.job import run_job
from pipeline.workflow.steps import ARTIFACTS_TAG, get_or_run
from pipeline.workflow.tracking import (
    EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, STEP_KIND, STEP_TAG, StoreError, ensure_experiment, step_run_tag,
)
from pipeline.core.world import WorldError, load_worlds

TOY = ["data=toy", "model=toy", "train=toy", "eval=toy"]
# Small enough to be quick, big enough to kill in the middle: 8 optimizer steps with a checkpoint every 4,
# and reachable episodes recorded one by one, two at a time.
# The paper's longer prompt keeps a step slow enough that the kill lands before the next logged step.
KILLABLE = [*TOY, "model.prompt=paper", "mode=reachable", "variant=no-all", "train.max_steps=8", "train.save_steps=4",
            "train.logging_steps=2", "eval.batch_size=2", "eval.max_new_tokens=48", "eval.max_moves=4",
            "hydra/job_logging=none"]
EXAMPLE_WORLD = {"question": {"world_size_x": 4, "world_size_y": 3, "wall": [[1, 1], [2, 2]], "pit": [[3, 0]],
                              "start": [0, 0], "goal": [3, 2], "gridstart_x": 0, "gridstart_y": 0}}


# ---------------------------------------------------------------------------------------------------- helpers
def _cfg(root, *overrides):
    return compose_job(root, *TOY, *overrides)


def _command(root, *overrides, multirun=False):
    return [sys.executable, "-m", "pipeline.run", *(["-m"] if multirun else []), f"tracking.root={root}", *overrides]


def _run_cli(root, *overrides, multirun=False, timeout=900):
    return subprocess.run(_command(root, *overrides, multirun=multirun), cwd=root, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _runs(root, kind=None, experiment="cogmap"):
    mlflow.set_tracking_uri(f"sqlite:///{root}/mlflow.db")
    query = f"tags.`{KIND_TAG}` = '{kind}'" if kind else ""
    return mlflow.search_runs(experiment_names=[experiment], filter_string=query, output_format="list",
                              order_by=["attributes.start_time ASC"])


def _step_runs(root, step):
    return [r for r in _runs(root, STEP_KIND) if r.data.tags[STEP_TAG] == step]


def _eval_metrics(root):
    (job,) = [r for r in _runs(root, JOB_KIND) if r.info.status == "FINISHED"]
    run = mlflow.get_run(job.data.tags[step_run_tag("eval")])
    return {k: v for k, v in run.data.metrics.items() if k != "step_seconds"}, run


def _episodes(run):  # from the store last searched
    path = mlflow.artifacts.download_artifacts(run_id=run.info.run_id, artifact_path=EPISODES_ARTIFACT)
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def _kill_when(root, overrides, ready, what, timeout=600):
    """Start the job, wait until ``ready()`` holds, kill -9 it; fail if it ends first."""
    log = open(root / f"killed-{what}.log", "w")
    process = subprocess.Popen(_command(root, *overrides), cwd=root, stdout=log, stderr=subprocess.STDOUT,
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


def _complete_checkpoints(root):
    return sorted(root.glob("work/finetune/*/checkpoints/checkpoint-*/trainer_state.json"))


def _partial_lines(root):
    files = list(root.glob("work/eval/*/episodes.partial.jsonl"))
    return files[0].read_text().splitlines() if files else []


def _loss_curve(run_id):
    history = mlflow.MlflowClient().get_metric_history(run_id, "loss")  # in the store last searched
    return {m.step: m.value for m in history}


# ---------------------------------------------------------------------------------------------------- 1. kill
@pytest.mark.slow
def test_kill_9_during_finetune_and_eval_then_rerun_equals_an_uninterrupted_run(tmp_path):
    reference, killed = tmp_path / "reference", tmp_path / "killed"
    reference.mkdir(), killed.mkdir()
    done = _run_cli(reference, *KILLABLE)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    expected, expected_eval = _eval_metrics(reference)
    expected_episodes = _episodes(expected_eval)
    (reference_finetune,) = _step_runs(reference, "finetune")
    reference_curve = _loss_curve(reference_finetune.info.run_id)
    assert sorted(reference_curve) == [2, 4, 6, 8]

    # 1st attempt: killed during finetune, once a checkpoint is complete (trainer_state.json comes last).
    _kill_when(killed, KILLABLE, lambda: _complete_checkpoints(killed), "a checkpoint")
    (data_run,) = _step_runs(killed, "data-build")
    (first_finetune,) = _step_runs(killed, "finetune")
    assert data_run.info.status == "FINISHED" and first_finetune.info.status == "RUNNING"  # as the kill left it

    # 2nd attempt: reuses data-build, resumes training, then is killed during eval with episodes recorded.
    _kill_when(killed, KILLABLE, lambda: len(_partial_lines(killed)) >= 2, "recorded episodes")
    before_rerun = _partial_lines(killed)
    assert 2 <= len(before_rerun) < 8
    finetunes = _step_runs(killed, "finetune")
    assert [r.info.status for r in finetunes] == ["KILLED", "FINISHED"]
    assert len(_step_runs(killed, "data-build")) == 1
    # Resumed, not restarted: the loss curve goes on after the checkpoint, equal value for value.
    assert _loss_curve(finetunes[0].info.run_id) == {step: reference_curve[step] for step in (2, 4)}
    assert _loss_curve(finetunes[1].info.run_id) == {step: reference_curve[step] for step in (6, 8)}

    # 3rd attempt: finishes, reusing data-build and finetune and the episodes already recorded.
    done = _run_cli(killed, *KILLABLE)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "reused: data-build, finetune" in done.stdout
    after = _partial_lines(killed)
    assert after[: len(before_rerun)] == before_rerun  # kept, not redone
    assert len(after) == 8 and len({json.loads(line)["world_index"] for line in after}) == 8

    metrics, eval_run = _eval_metrics(killed)
    assert metrics == expected
    assert _episodes(eval_run) == expected_episodes
    assert [r.info.status for r in _step_runs(killed, "eval")] == ["KILLED", "FINISHED"]
    statuses = [r.info.status for r in _runs(killed, JOB_KIND)]
    assert statuses == ["KILLED", "KILLED", "FINISHED"]  # never left RUNNING, never looking finished
    assert all(r.info.status in ("FINISHED", "KILLED") for r in _runs(killed))


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


# ---------------------------------------------------------------------------------------------------- 2. parallel
@pytest.mark.slow
def test_two_parallel_workers_on_a_fresh_store_run_every_job_once(tmp_path):
    # none texts do not depend on the direction: both jobs need the same data-build and finetune, at once.
    done = _run_cli(tmp_path, "hydra/launcher=local2", "threads=1", *TOY, "variant=none", "direction=fwd,bwd",
                    "train.max_steps=2", "eval.n_worlds=3", "eval.max_new_tokens=32", multirun=True)
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-4000:]
    assert "Traceback" not in output and "Error executing job" not in output
    jobs = _runs(tmp_path, JOB_KIND)
    assert len(jobs) == 2 and all(r.info.status == "FINISHED" for r in jobs)
    assert {r.data.tags["direction"] for r in jobs} == {"fwd", "bwd"}
    steps = _runs(tmp_path, STEP_KIND)
    assert all(r.info.status == "FINISHED" for r in steps)
    # One run per step hash: the second worker waited on the lock and reused what the first made.
    assert sorted(r.data.tags[STEP_TAG] for r in steps) == ["data-build", "eval", "finetune"]
    assert len({r.data.tags[step_run_tag("finetune")] for r in jobs}) == 1
    assert sum("reused: data-build, finetune, eval" in line for line in done.stdout.splitlines()) == 1
    assert (tmp_path / "report" / "report.md").is_file()


# ---------------------------------------------------------------------------------------------------- 3. bad input
@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """One store for the bad-input jobs (a new SQLite store costs seconds; data-build is shared)."""
    return tmp_path_factory.mktemp("bad-input")


def _world_file(folder: Path, name: str, *lines: object) -> Path:
    path = folder / name
    path.write_bytes(b"".join(line if isinstance(line, bytes) else (json.dumps(line) + "\n").encode()
                              for line in lines))
    return path


def _with(**changes):
    return {"question": {**EXAMPLE_WORLD["question"], **changes}}


@pytest.mark.parametrize("name, bad_line, message", [
    ("malformed", b'{"question": {"world_size_x": 4,\n', r"malformed.jsonl:2: .*(Expecting|delimiter)"),
    ("two-paths", _with(wall=[], pit=[], world_size_x=2, world_size_y=2, goal=[1, 1]),
     r"two-paths.jsonl:2: more than one shortest path from \(0, 0\) to \(1, 1\)"),
    ("negative", _with(world_size_x=-3), r"negative.jsonl:2: size_x=-3 is too small; allowed: 2 or more"),
    ("zero", _with(world_size_y=0), r"zero.jsonl:2: size_y=0 is too small; allowed: 2 or more"),
    ("huge", _with(world_size_x=10**6, world_size_y=10**6), r"huge.jsonl:2: .*cells; allowed: at most"),
    ("binary", b"\xff\xfe\x00garbage\n", r"binary.jsonl:2: not UTF-8"),
    ("schema", {"world": 1}, r"schema.jsonl:2: expected an object with key 'question'"),
])
def test_a_bad_world_file_is_refused_naming_file_line_and_rule(tmp_path, name, bad_line, message):
    path = _world_file(tmp_path, f"{name}.jsonl", EXAMPLE_WORLD, bad_line)
    cfg = _cfg(tmp_path, f"data.test_file={path}", "data.n_test=2")
    with pytest.raises(ConfigError, match=f"data.test_file=.*{message}"):
        run_job(cfg)
    assert not (tmp_path / "mlflow.db").exists()  # refused at validation, before any work
    with pytest.raises(WorldError, match=message):  # and the loader itself names the same line and rule
        load_worlds(path)


@pytest.mark.parametrize("overrides, error, message", [
    (["data.test_file=/no/such/worlds.jsonl"], ConfigError, r"data.test_file=./no/such/worlds.jsonl.: no such file"),
    (["data.n_test=5"], ConfigError, r"data.n_test=5 but data.test_file=.* holds 1 worlds; allowed: 1..1"),
    (["eval.n_worlds=9"], ConfigError, r"eval.n_worlds=9: .*allowed: 1..8"),
    (["data.train_size_x=[0,3]"], ConfigError, r"data.train_size_x=\[0, 3\] is not allowed; expected 2 <= min"),
    (["data.n_train=-1"], ConfigError, r"data.n_train=-1 is not allowed; expected at least 1"),
])
def test_bad_data_and_eval_values_are_refused_naming_them(store, overrides, error, message):
    if any("n_test=5" in o for o in overrides):
        overrides = [*overrides, f"data.test_file={_world_file(store, 'one.jsonl', EXAMPLE_WORLD)}"]
    with pytest.raises(error, match=message):
        run_job(_cfg(store, *overrides))


def _model_dir(folder: Path, weights: bytes | None) -> Path:
    from pipeline.lm.models import build_scratch_model
    from pipeline.lm.tokenizer import build_word_tokenizer

    tokenizer = build_word_tokenizer(["Plan:\nup"], frame=5)
    model = build_scratch_model(tokenizer, hidden_size=16, num_layers=1, num_heads=2, intermediate_size=16)
    folder.mkdir()
    model.config.save_pretrained(folder)
    tokenizer.save_pretrained(folder)
    if weights is not None:
        (folder / "model.safetensors").write_bytes(weights)
    return folder


@pytest.mark.parametrize("case, message", [
    ("missing", r"missing-model.*(no such directory|expected a local)"),
    ("no-weights", r"no-weights-model.*safetensors"),
    ("corrupt", r"corrupt-model: cannot load the model"),
    ("pickle-only", r"pickle-only-model.*safetensors"),
])
def test_a_missing_or_corrupt_model_is_refused_naming_its_path(store, case, message):
    path = store / f"{case}-model"
    if case == "corrupt":
        _model_dir(path, b"\x00not safetensors" * 8)
    elif case == "no-weights":
        _model_dir(path, None)
    elif case == "pickle-only":  # a pytorch_model.bin would run pickle code: never loaded
        _model_dir(path, None)
        (path / "pytorch_model.bin").write_bytes(b"\x80\x04 pickle")
    with pytest.raises((ModelLoadError, ConfigError), match=message):
        run_job(_cfg(store, "model=hf", f"model.path={path}"))
    finetunes = [r for r in _runs(store, STEP_KIND) if r.data.tags[STEP_TAG] == "finetune"]
    assert all(r.info.status != "FINISHED" for r in finetunes)


def test_an_unwritable_output_folder_is_refused_naming_it(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    started = time.monotonic()
    with pytest.raises(ConfigError, match=f"{blocker}.*is not a writable folder"):
        run_job(_cfg(blocker / "outputs"))
    assert time.monotonic() - started < 20


def test_an_unwritable_output_folder_fails_the_command_naming_it(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    done = _run_cli(tmp_path, "data=toy", f"tracking.root={blocker}/outputs", timeout=120)
    assert done.returncode != 0 and f"{blocker}/outputs" in done.stdout + done.stderr


def test_an_unreachable_tracking_server_fails_fast(tmp_path):
    started = time.monotonic()
    with pytest.raises(ConfigError, match=r"tracking.uri='http://127.0.0.1:9'.*did not answer"):
        run_job(_cfg(tmp_path, "tracking.uri=http://127.0.0.1:9"))
    assert time.monotonic() - started < 20  # MLflow's own retries would take minutes


def test_a_deleted_experiment_is_named_not_written_into(tmp_path):
    cfg = _cfg(tmp_path)
    experiment_id = ensure_experiment(cfg.tracking.uri, "cogmap", str(tmp_path / "mlartifacts"))
    mlflow.delete_experiment(experiment_id)
    with pytest.raises(ConfigError, match="experiment 'cogmap' .* is deleted; restore it"):
        run_job(cfg)
    with pytest.raises(StoreError):
        ensure_experiment(cfg.tracking.uri, "cogmap", str(tmp_path / "mlartifacts"))


@pytest.mark.parametrize("override, allowed", [
    ("variant=bogus", "no-marking-no-backtrack"),  # a config group: Hydra lists the options
    ("train.max_steps=-5", "a positive integer"),  # a value: our validation names the rule
])
def test_the_command_line_names_a_bad_value_and_what_is_allowed(tmp_path, override, allowed):
    done = _run_cli(tmp_path, "data=toy", override, timeout=120)
    output = done.stdout + done.stderr
    assert done.returncode != 0
    assert override.split("=")[1] in output and allowed in output
    assert "Traceback" not in output  # a message for people, not a crash
    assert not (tmp_path / "mlflow.db").exists()  # refused before any work


def test_a_bad_value_is_one_line_and_hydra_full_error_shows_the_trace(tmp_path):
    done = _run_cli(tmp_path, "data=toy", "data.train_size_x=[5,3]", timeout=120)
    assert done.returncode == 2 and done.stderr.strip().splitlines() == [
        "error: data.train_size_x=[5, 3] is not allowed; expected 2 <= min <= max <= frame (5)"]
    traced = subprocess.run(_command(tmp_path, "data=toy", "data.train_size_x=[5,3]"), cwd=tmp_path,
                            capture_output=True, text=True, timeout=120, env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert traced.returncode != 0 and "Traceback" in traced.stderr and "ConfigError" in traced.stderr


@pytest.mark.slow
def test_two_commands_started_together_on_a_new_store_both_finish_and_share_their_steps(tmp_path):
    overrides = [*TOY, "train.max_steps=2", "eval.n_worlds=2", "eval.max_new_tokens=16", "hydra/job_logging=none"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    processes = [subprocess.Popen(_command(tmp_path, *overrides), cwd=tmp_path, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, env=env) for _ in range(2)]
    outputs = [process.communicate(timeout=600)[0] for process in processes]
    assert [process.returncode for process in processes] == [0, 0], "\n".join(o[-2000:] for o in outputs)
    assert all("Traceback" not in output for output in outputs)
    jobs = _runs(tmp_path, JOB_KIND)
    assert [job.info.status for job in jobs] == ["FINISHED", "FINISHED"]
    for step in ("data-build", "finetune", "eval"):
        assert len(_step_runs(tmp_path, step)) == 1  # one ran it, the other reused it


@pytest.mark.slow
def test_a_sweep_with_a_bad_job_finishes_the_others_and_keeps_their_results(tmp_path):
    # Job 1 asks for more test worlds than the split has; jobs 0 and 2 share data-build and finetune.
    done = _run_cli(tmp_path, *TOY, "train.max_steps=2", "eval.max_new_tokens=32", "eval.n_worlds=2,99,3",
                    multirun=True)
    output = done.stdout + done.stderr
    assert done.returncode != 0
    assert "eval.n_worlds=99" in output and "allowed: 1..8" in output
    summaries = [line for line in done.stdout.splitlines() if line.startswith("[job]")]
    assert len(summaries) == 2 and "over 2 worlds" in summaries[0] and "over 3 worlds" in summaries[1]
    jobs = _runs(tmp_path, JOB_KIND)
    assert [r.info.status for r in jobs] == ["FINISHED", "FINISHED"]
    assert sorted(r.data.metrics["n_episodes"] for r in jobs) == [2.0, 3.0]
    assert all(r.info.status == "FINISHED" for r in _runs(tmp_path, STEP_KIND))


# ---------------------------------------------------------------------------------------------------- 4. determinism
@pytest.mark.slow
def test_the_same_config_twice_gives_identical_hashes_records_and_metrics(tmp_path):
    # model.max_length=58: the larger test worlds' prompts (58-63 tokens of 47-63, task prompt) no longer fit the
    # context, so this also shows a too-large test world becoming a per-episode error while the job finishes.
    overrides = ["train.max_steps=2", "eval.max_new_tokens=32", "model.max_length=58"]
    results = []
    for name in ("a", "b"):
        root = tmp_path / name
        metrics = run_job(_cfg(root, *overrides))
        data = _step_runs(root, "data-build")[0]
        (finetune,) = _step_runs(root, "finetune")
        (evaluation,) = _step_runs(root, "eval")
        results.append({
            "metrics": {k: v for k, v in metrics.items() if k != "step_seconds"},
            "hashes": [run.data.tags["cogmap.hash"] for run in (data, finetune, evaluation)],
            "dataset_sha256": data.data.tags["dataset_sha256"],
            "final_loss": finetune.data.metrics["final_loss"],
            "episodes": _episodes(evaluation),
        })
    assert results[0] == results[1]
    episodes = results[0]["episodes"]
    errors = [r for r in episodes if r["outcome"] == "error"]
    assert errors and len(errors) < len(episodes)
    assert all("context of 58" in r["error"] and r["success"] is False for r in errors)
    assert results[0]["metrics"]["rate_error"] == len(errors) / len(episodes)


# ---------------------------------------------------------------------------------------------------- 6. safety
def test_models_load_from_safetensors_only_and_remote_code_only_on_request():
    import inspect

    from pipeline.lm import models as modeling

    source = inspect.getsource(modeling.load_model)
    assert "use_safetensors=True" in source and "trust_remote_code=trust_remote_code" in source
    assert inspect.signature(modeling.load_model).parameters["trust_remote_code"].default is False
    assert inspect.signature(modeling.load_tokenizer).parameters["trust_remote_code"].default is False
    assert ModelSettings().trust_remote_code is False   # the base every model preset starts from
    for option in sorted((ROOT / "conf" / "model").glob("*.yaml")):
        assert _cfg(ROOT / "outputs", f"model={option.stem}", "model.path=x").model.trust_remote_code is False, option.name


def _readme_commands(text: str) -> list[str]:
    """Shell commands in a Markdown text: the lines of fenced blocks and the inline code spans."""
    import re

    fenced = re.findall(r"```[^\n]*\n(.*?)```", text, flags=re.S)
    lines = [line for block in fenced for line in block.replace("\\\n", " ").splitlines()]
    inline = re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
    return [command.strip().lstrip("$ ") for command in lines + inline]


def test_the_readme_binds_mlflow_ui_to_localhost():
    readme = ROOT / "README.md"
    if not readme.exists():
        pytest.skip("README.md not written yet")
    commands = [c for c in _readme_commands(readme.read_text()) if c.startswith(("mlflow ui", "mlflow server"))]
    assert commands, "the README should say how to open the MLflow UI"
    for command in commands:
        assert "--host 127.0.0.1" in command or "-h 127.0.0.1" in command, command
