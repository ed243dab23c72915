"""Bad input, end to end (a dozen kinds): an early error naming the value and what is allowed, or a
per-episode error record; a sweep with a bad job keeps the others' results."""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path

import mlflow
import pytest

from pipeline.workflow.config import ConfigError
from pipeline.lm.models import ModelLoadError
from pipeline.workflow.job import run_job
from pipeline.workflow.tracking import (
    JOB_KIND, STEP_KIND, STEP_TAG, StoreError, ensure_experiment,
)
from pipeline.core.world import WorldError, load_worlds
from jobs import EXAMPLE_WORLD, TOY, cli_command, run_cli, step_runs, store_runs, toy_config



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
    cfg = toy_config(tmp_path, f"data.test_file={path}", "data.n_test=2")
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
        run_job(toy_config(store, *overrides))


def _model_dir(folder: Path, weights: bytes | None) -> Path:
    from pipeline.lm.model_settings import ModelSettings
    from pipeline.lm.models import build_scratch_model
    from pipeline.lm.tokenizer import build_word_tokenizer

    tokenizer = build_word_tokenizer(["Plan:\nup"], frame=5)
    model = build_scratch_model(tokenizer, ModelSettings(hidden_size=16, num_layers=1, num_heads=2, intermediate_size=16))
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
        run_job(toy_config(store, "model=hf", f"model.path={path}"))
    finetunes = [r for r in store_runs(store, STEP_KIND) if r.data.tags[STEP_TAG] == "finetune"]
    assert all(r.info.status != "FINISHED" for r in finetunes)


def test_an_unwritable_output_folder_is_refused_naming_it(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    started = time.monotonic()
    with pytest.raises(ConfigError, match=f"{blocker}.*is not a writable folder"):
        run_job(toy_config(blocker / "outputs"))
    assert time.monotonic() - started < 20


def test_an_unwritable_output_folder_fails_the_command_naming_it(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    done = run_cli(tmp_path, "data=toy", f"tracking.root={blocker}/outputs", timeout=120)
    assert done.returncode != 0 and f"{blocker}/outputs" in done.stdout + done.stderr


def test_an_unreachable_tracking_server_fails_fast(tmp_path):
    started = time.monotonic()
    with pytest.raises(ConfigError, match=r"tracking.uri='http://127.0.0.1:9'.*did not answer"):
        run_job(toy_config(tmp_path, "tracking.uri=http://127.0.0.1:9"))
    assert time.monotonic() - started < 20  # MLflow's own retries would take minutes


def test_a_deleted_experiment_is_named_not_written_into(tmp_path):
    cfg = toy_config(tmp_path)
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
    done = run_cli(tmp_path, "data=toy", override, timeout=120)
    output = done.stdout + done.stderr
    assert done.returncode != 0
    assert override.split("=")[1] in output and allowed in output
    assert "Traceback" not in output  # a message for people, not a crash
    assert not (tmp_path / "mlflow.db").exists()  # refused before any work


def test_a_bad_value_is_one_line_and_hydra_full_error_shows_the_trace(tmp_path):
    done = run_cli(tmp_path, "data=toy", "data.train_size_x=[5,3]", timeout=120)
    assert done.returncode == 2 and done.stderr.strip().splitlines() == [
        "error: data.train_size_x=[5, 3] is not allowed; expected 2 <= min <= max <= frame (5)"]
    traced = subprocess.run(cli_command(tmp_path, "data=toy", "data.train_size_x=[5,3]"), cwd=tmp_path,
                            capture_output=True, text=True, timeout=120, env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert traced.returncode != 0 and "Traceback" in traced.stderr and "ConfigError" in traced.stderr


@pytest.mark.slow
def test_two_commands_started_together_on_a_new_store_both_finish_and_share_their_steps(tmp_path):
    overrides = [*TOY, "train.max_steps=2", "eval.n_worlds=2", "eval.max_new_tokens=16", "hydra/job_logging=none"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    processes = [subprocess.Popen(cli_command(tmp_path, *overrides), cwd=tmp_path, stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True, env=env) for _ in range(2)]
    outputs = [process.communicate(timeout=600)[0] for process in processes]
    assert [process.returncode for process in processes] == [0, 0], "\n".join(o[-2000:] for o in outputs)
    assert all("Traceback" not in output for output in outputs)
    jobs = store_runs(tmp_path, JOB_KIND)
    assert [job.info.status for job in jobs] == ["FINISHED", "FINISHED"]
    for step in ("data-build", "finetune", "eval"):
        assert len(step_runs(tmp_path, step)) == 1  # one ran it, the other reused it


@pytest.mark.slow
def test_a_sweep_with_a_bad_job_finishes_the_others_and_keeps_their_results(tmp_path):
    # Job 1 asks for more test worlds than the split has; jobs 0 and 2 share data-build and finetune.
    done = run_cli(tmp_path, *TOY, "train.max_steps=2", "eval.max_new_tokens=32", "eval.n_worlds=2,99,3",
                    multirun=True)
    output = done.stdout + done.stderr
    assert done.returncode != 0
    assert "eval.n_worlds=99" in output and "allowed: 1..8" in output
    summaries = [line for line in done.stdout.splitlines() if line.startswith("[job]")]
    assert len(summaries) == 2 and "over 2 worlds" in summaries[0] and "over 3 worlds" in summaries[1]
    jobs = store_runs(tmp_path, JOB_KIND)
    assert [r.info.status for r in jobs] == ["FINISHED", "FINISHED"]
    assert sorted(r.data.metrics["n_episodes"] for r in jobs) == [2.0, 3.0]
    assert all(r.info.status == "FINISHED" for r in store_runs(tmp_path, STEP_KIND))


def test_a_test_file_with_a_repeated_world_is_refused_naming_the_lines(tmp_path):
    """Repeated worlds would be scored as distinct episodes (counted twice, intervals too narrow)."""
    other = _with(world_size_x=2, world_size_y=2, goal=[1, 1], wall=[[1, 0]], pit=[])
    path = _world_file(tmp_path, "repeats.jsonl", EXAMPLE_WORLD, other, EXAMPLE_WORLD)
    with pytest.raises(ConfigError, match=r"data.test_file=.*1 world\(s\) repeat an earlier one \(line 3 repeats "
                                          r"line 1\); allowed: a file of distinct worlds"):
        run_job(toy_config(tmp_path, f"data.test_file={path}", "data.n_test=3"))
    assert not (tmp_path / "mlflow.db").exists()


@pytest.mark.parametrize("override, named", [("+trian.lr=5", "trian"), ("+train.lrr=5", "train.lrr"),
                                             ("+model.chat_format.bos=x", None)])
def test_an_added_key_the_schema_lacks_is_refused_before_any_work(tmp_path, override, named):
    """`+key=value` adds any key to the structured config; a typo must not run with the key ignored."""
    if named is None:  # '+' on a key the schema has is Hydra's own error ("already exists"), at compose time
        with pytest.raises(Exception, match="already"):
            toy_config(tmp_path, override)
        return
    with pytest.raises(ConfigError, match=rf"unknown config key\(s\) {named} \(added with '\+'\?\)"):
        run_job(toy_config(tmp_path, override))
    assert not (tmp_path / "mlflow.db").exists()
