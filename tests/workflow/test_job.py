"""The main path, end to end at toy scale: a job's three steps, their reuse, and a real Hydra multirun."""

import json
import re
import subprocess
import sys
from pathlib import Path

import mlflow
import pytest
import torch
from omegaconf import OmegaConf
from safetensors.torch import load_file
from conftest import ROOT, compose_job

from pipeline.workflow.config import ConfigError
from pipeline.workflow.job import run_job
from pipeline.core.episodes import EPISODE_FIELDS
from pipeline.workflow.data_build import TEST_WORLDS
from pipeline.workflow.tracking import EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, step_run_tag

TOY = ["data=toy", "model=toy", "train=toy", "eval=toy", "train.max_steps=2", "eval.n_worlds=3",
       "eval.max_new_tokens=48"]


def _cfg(tmp_path, *overrides):
    return compose_job(tmp_path, *TOY, *overrides)


def _job_runs(cfg):
    mlflow.set_tracking_uri(cfg.tracking.uri)
    return mlflow.search_runs(experiment_names=[cfg.tracking.experiment], output_format="list",
                              filter_string=f"tags.`{KIND_TAG}` = '{JOB_KIND}'", order_by=["attributes.start_time ASC"])


@pytest.mark.slow
def test_a_job_runs_its_steps_then_reuses_them(tmp_path):
    cfg = _cfg(tmp_path, "variant=no-all", "direction=fwd")
    first = run_job(cfg)
    assert first["n_episodes"] == 3 and 0.0 <= first["success_rate"] <= 1.0
    again = run_job(cfg)
    assert again == first
    changed_eval = run_job(_cfg(tmp_path, "variant=no-all", "direction=fwd", "eval.n_worlds=2"))
    runs = _job_runs(cfg)
    assert len(runs) == 3 and all(r.info.status == "FINISHED" for r in runs)
    ids = [{step: r.data.tags[step_run_tag(step)] for step in ("data-build", "finetune", "eval")} for r in runs]
    assert ids[0] == ids[1]
    assert ids[2]["finetune"] == ids[0]["finetune"] and ids[2]["eval"] != ids[0]["eval"]
    assert changed_eval["n_episodes"] == 2
    tags = runs[0].data.tags
    assert (tags["direction"], tags["variant"], tags["mode"], tags["paper_row"]) == ("fwd", "no-all", "optimal", "w.o. ALL")
    records = [json.loads(line) for line in open(mlflow.artifacts.download_artifacts(
        run_id=ids[0]["eval"], artifact_path=EPISODES_ARTIFACT, tracking_uri=cfg.tracking.uri))]
    assert [r["world_index"] for r in records] == [0, 1, 2] and set(records[0]) == set(EPISODE_FIELDS)
    assert all(len(r["answers"]) == 1 and isinstance(r["answers"][0], str) for r in records)
    client = mlflow.MlflowClient(cfg.tracking.uri)
    contexts = {step: sorted(tag.value for entry in client.get_run(ids[0][step]).inputs.dataset_inputs
                             for tag in entry.tags if tag.key == "mlflow.data.context")
                for step in ("data-build", "finetune", "eval")}
    assert contexts == {"data-build": ["test", "train"], "finetune": ["training"], "eval": ["evaluation"]}
    train_input = client.get_run(ids[0]["finetune"]).inputs.dataset_inputs[0].dataset
    assert train_input.name == "fwd-no-all-optimal-train" and "conversations/train.jsonl" in train_input.source
    experiment = client.get_experiment_by_name(cfg.tracking.experiment)
    assert experiment.tags["mlflow.experimentKind"] == "custom_model_development"


@pytest.mark.slow
def test_the_finetuned_model_is_an_mlflow_model_and_inspect_shows_its_answers(tmp_path):
    import mlflow.transformers

    from pipeline.report.answers import inspect_run, main as inspect_main

    cfg = _cfg(tmp_path, "variant=marking-deadend", "eval.n_worlds=2", "eval.n_valid=2")
    run_job(cfg)
    job = _job_runs(cfg)[0]
    finetune_id = job.data.tags[step_run_tag("finetune")]
    models = mlflow.search_logged_models(experiment_ids=[job.info.experiment_id], output_format="list",
                                         filter_string=f"source_run_id = '{finetune_id}'")
    assert len(models) == 1
    pipe = mlflow.transformers.load_model(f"models:/{models[0].model_id}")
    saved = load_file(str(next(Path(mlflow.artifacts.download_artifacts(
        run_id=finetune_id, artifact_path="model", tracking_uri=cfg.tracking.uri)).glob("*.safetensors"))))
    weights = pipe.model.state_dict()
    assert all(torch.equal(weights[name], tensor) for name, tensor in saved.items() if name in weights)
    text = inspect_run(cfg.tracking.uri, job.info.run_id, world=1)
    assert "world 1 (" in text and "--- task prompt\nGrid is from" in text
    assert "answer (" in text and "golden" in text and "Thought:" in text
    eval_id = job.data.tags[step_run_tag("eval")]
    assert inspect_run(cfg.tracking.uri, eval_id, world=1) == text
    assert inspect_main([eval_id, "--world", "7", "--tracking-uri", cfg.tracking.uri]) == 2
    # The command line, named as jobs name the store: the answer alone, no download bars before it.
    done = subprocess.run([sys.executable, "-m", "pipeline.inspect", eval_id, "--world", "1",
                           f"tracking.root={tmp_path}"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.split("\n", 1)[1] == text.split("\n", 1)[1]
    assert "Downloading artifacts" not in done.stdout + done.stderr
    # The teacher-forced probe of the same model: a row per kind of neighbour with counts that add up to the
    # labels of the first world's golden answer, then a row per kind of line with counts that add up to its lines.
    from pipeline.core.map_errors import NEIGHBOURS, PROBE_KINDS, corner_offset, label_cells, label_kinds, line_kinds
    from pipeline.core.world import load_worlds
    from pipeline.report.answers import InspectError, probe_labels

    from pipeline.workflow.data_build import TRAIN_WORLDS, DataSettings, validation_worlds

    def counted(text):
        blocks = [block.splitlines() for block in text.split("\n\n")]
        assert [row.split()[0] for row in blocks[1][1:]] == list(NEIGHBOURS)
        assert {row[:14].strip() for row in blocks[2][1:]} <= set(PROBE_KINDS)
        return [sum(int(n) for row in block[1:] for n in re.findall(r"\(\d+/(\d+)\)", row)) for block in blocks[1:3]]

    def artifact(name):
        return load_worlds(mlflow.artifacts.download_artifacts(
            run_id=job.data.tags[step_run_tag("data-build")], artifact_path=name, tracking_uri=cfg.tracking.uri))

    # By default the validation worlds (drawn again as the eval step drew them); --split test: the test worlds.
    test = artifact(TEST_WORLDS)
    data = OmegaConf.to_object(cfg.data)
    valid = validation_worlds(data, 2, artifact(TRAIN_WORLDS), test)[0]
    graded = probe_labels(cfg.tracking.uri, job.info.run_id, limit=1)
    assert "1 validation worlds, each fed" in graded
    assert counted(graded) == [len(label_kinds(valid, "bwd", "marking-deadend")),
                               len(line_kinds(valid, "bwd", "marking-deadend"))]
    graded = probe_labels(cfg.tracking.uri, job.info.run_id, limit=1, split="test")
    assert "1 test worlds, each fed" in graded
    with pytest.raises(InspectError, match="'train': one of valid, test"):
        probe_labels(cfg.tracking.uri, job.info.run_id, split="train")
    assert counted(graded) == [len(label_kinds(test[0], "bwd", "marking-deadend")),
                               len(line_kinds(test[0], "bwd", "marking-deadend"))]
    # Beyond the training sizes (toy: sides 2..3), the new free cells' labels again, by their offset.
    free = sorted(corner_offset(test[0], cell) for _, kind, cell in label_cells(test[0], "bwd", "marking-deadend")
                  if kind == "free")
    by_offset = graded.split("by their offset from the grid's low corner")
    if max(test[0].size_x, test[0].size_y) > 3:
        rows = by_offset[1].strip().splitlines()[2:]
        assert [int(row.split()[0]) for row in rows] == sorted(set(free))
        assert sum(int(n) for row in rows for n in re.findall(r"\(\d+/(\d+)\)", row)) == len(free)
    else:
        assert len(by_offset) == 1
    with pytest.raises(SystemExit):
        inspect_main([eval_id, "--labels", "--world", "1", "--tracking-uri", cfg.tracking.uri])
    from pipeline.report.build import main as report_main

    assert report_main([f"tracking.root={tmp_path}", "--no-log-run"]) == 0
    assert (tmp_path / "report" / "report.md").is_file()


@pytest.mark.slow
def test_reachable_job_records_outcomes(tmp_path):
    cfg = _cfg(tmp_path, "variant=dfs", "eval.max_moves=5")
    metrics = run_job(cfg)
    assert metrics["n_episodes"] == 3
    eval_id = _job_runs(cfg)[0].data.tags[step_run_tag("eval")]
    records = [json.loads(line) for line in open(mlflow.artifacts.download_artifacts(
        run_id=eval_id, artifact_path=EPISODES_ARTIFACT, tracking_uri=cfg.tracking.uri))]
    assert all(len(r["answers"]) >= 1 and len(r["answers"]) >= r["n_moves"] for r in records)
    assert abs(sum(metrics.get(k, 0.0) for k in ("success_rate", "rate_deadend", "rate_max_step", "rate_invalid",
                                                   "rate_error")) - 1.0) < 1e-9


def test_an_impossible_combination_fails_before_any_work(tmp_path):
    with pytest.raises(ConfigError, match="mode=reachable"):
        run_job(_cfg(tmp_path, "variant=dfs", "mode=optimal"))
    assert not (tmp_path / "mlflow.db").exists()


def test_an_undefined_grid_cell_is_skipped_when_asked(tmp_path):
    assert run_job(_cfg(tmp_path, "variant=dfs", "mode=optimal", "skip_undefined=true")) is None


@pytest.mark.slow
def test_smoke_sweep_runs_the_whole_grid(tmp_path):
    """The README's smoke sweep, as a user runs it (a real Hydra multirun in a subprocess)."""
    command = [sys.executable, "-m", "pipeline.run", "-m", "--config-dir", str(ROOT / "sweeps"),
               "--config-name", "smoke", f"tracking.root={tmp_path}"]
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=1500)
    assert done.returncode == 0, done.stderr[-3000:]
    summaries = [line for line in done.stdout.splitlines() if line.startswith("[job]")]
    assert len(summaries) == 34  # 2 directions x 8 variants x 2 settings + dfs (reachable) x 2 directions
    assert sum("skipped" in line for line in done.stdout.splitlines() + done.stderr.splitlines()) >= 2
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/mlflow.db")
    jobs = mlflow.search_runs(experiment_names=["cogmap"], output_format="list",
                              filter_string=f"tags.`{KIND_TAG}` = '{JOB_KIND}'")
    assert len(jobs) == 34 and all(r.info.status == "FINISHED" for r in jobs)
    finetunes = {r.data.tags[step_run_tag("finetune")] for r in jobs}
    assert len(finetunes) == 31  # none and dfs texts do not depend on the direction: shared
    assert (tmp_path / "report").is_dir()


def test_a_large_models_logged_model_is_a_reference_to_the_runs_weights(tmp_path):
    # model.log_model=reference (the hf and llama3_8b presets): no second copy of the weights in the store.
    cfg = _cfg(tmp_path, "variant=none", "eval.n_worlds=1", "model.log_model=reference")
    run_job(cfg)
    job = _job_runs(cfg)[0]
    finetune_id = job.data.tags[step_run_tag("finetune")]
    (model,) = mlflow.search_logged_models(experiment_ids=[job.info.experiment_id], output_format="list",
                                           filter_string=f"source_run_id = '{finetune_id}'")
    assert model.params["weights"] == f"runs:/{finetune_id}/model"
    # Only an MLmodel file: no weights copied.
    assert [f.path for f in mlflow.artifacts.list_artifacts(artifact_uri=model.artifact_location)] == ["artifacts/MLmodel"]


@pytest.mark.slow
def test_checkpoint_curve_is_logged_by_training_step(tmp_path):
    cfg = _cfg(tmp_path, "variant=none", "train.max_steps=4", "train.save_steps=2", "train.log_checkpoints=true",
               "eval.curve=true", "eval.curve_worlds=2")
    run_job(cfg)
    job = _job_runs(cfg)[-1]
    history = mlflow.MlflowClient().get_metric_history(job.data.tags[step_run_tag("eval")], "curve_success_rate")
    assert sorted(m.step for m in history) == [2, 4]
    assert all(0.0 <= m.value <= 1.0 for m in history)


@pytest.mark.slow
def test_the_validation_curve_scores_each_checkpoint_on_every_validation_world(tmp_path):
    cfg = _cfg(tmp_path, "variant=none", "train.max_steps=4", "train.save_steps=2", "train.log_checkpoints=true",
               "eval.curve=true", "eval.curve_worlds=2", "eval.n_valid=3", "eval.curve_valid=true")
    run_job(cfg)
    client, eval_id = mlflow.MlflowClient(), _job_runs(cfg)[-1].data.tags[step_run_tag("eval")]
    for name in ("curve_success_rate", "valid_curve_success_rate"):
        history = client.get_metric_history(eval_id, name)
        assert sorted(m.step for m in history) == [2, 4] and all(0.0 <= m.value <= 1.0 for m in history)
    episodes = [client.download_artifacts(eval_id, f"valid_curve/step-{step}.jsonl", str(tmp_path)) for step in (2, 4)]
    assert [len(Path(path).read_text().splitlines()) for path in episodes] == [3, 3]
    # The last checkpoint is the final model: its validation curve point is the validation score itself.
    final = client.get_run(eval_id).data.metrics["valid_success_rate"]
    assert max(client.get_metric_history(eval_id, "valid_curve_success_rate"), key=lambda m: m.step).value == final


def test_a_curve_without_logged_checkpoints_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="train.log_checkpoints=true"):
        run_job(_cfg(tmp_path, "eval.curve=true"))


# accelerate's single-process launcher: the same `accelerate launch` path as FSDP, on one device.
SINGLE_PROCESS = """compute_environment: LOCAL_MACHINE
distributed_type: 'NO'
num_processes: 1
num_machines: 1
mixed_precision: 'no'
"""


@pytest.mark.slow
def test_a_launched_finetune_trains_exactly_what_the_in_process_one_does(tmp_path):
    exact = not torch.cuda.is_available()  # GPU kernels are not bitwise deterministic; the CPU's are
    config = tmp_path / "single.yaml"
    config.write_text(SINGLE_PROCESS)
    # One thread in both processes: the launcher sets its own thread count, and sums split differently.
    in_process = _cfg(tmp_path, "variant=none", "train.torch_threads=1")
    launched = _cfg(tmp_path, "variant=none", "train.torch_threads=1", f"train.accelerate_config={config}")
    scores = [run_job(launched), run_job(in_process)]
    for metrics in scores:
        metrics.pop("step_seconds")  # wall time
    if exact:
        assert scores[0] == scores[1]
    else:  # GPU kernels are not bitwise deterministic: the same scores within a few episodes
        assert scores[0]["success_rate"] == pytest.approx(scores[1]["success_rate"], abs=0.05)
    client = mlflow.MlflowClient(launched.tracking.uri)
    runs = [client.get_run(r.data.tags[step_run_tag("finetune")]) for r in _job_runs(launched)]
    assert runs[0].info.run_id != runs[1].info.run_id
    # The launched process logged into the step's run: the Trainer's curve and the summary metrics.
    assert [m.step for m in client.get_metric_history(runs[0].info.run_id, "loss")] == [2]  # toy: logging_steps=2
    first, second = (r.data.metrics for r in runs)
    assert (first["tokens_trained"], first["global_step"]) == (second["tokens_trained"], second["global_step"])
    assert first["final_loss"] == (second["final_loss"] if exact else pytest.approx(second["final_loss"], rel=1e-3))
    weights = [load_file(Path(mlflow.artifacts.download_artifacts(run_id=r.info.run_id, artifact_path="model",
                                                                  tracking_uri=launched.tracking.uri))
                         / "model.safetensors") for r in runs]
    assert weights[0].keys() == weights[1].keys()
    for key in weights[0]:
        if exact:
            assert torch.equal(weights[0][key], weights[1][key]), key
        else:
            torch.testing.assert_close(weights[0][key].float(), weights[1][key].float(), rtol=1e-2, atol=1e-3)


def test_plain_headers_nope_model_and_validation_split_run_end_to_end(tmp_path, capsys):
    """The extrapolation switches through a whole job: the data are written with plain headers, the model is
    built without RoPE and its tokenizer cuts numbers into digits and joins each newline to the word before it,
    and eval.n_valid scores the validation worlds apart from the test worlds."""
    cfg = _cfg(tmp_path, "model.step_headers=plain", "model.positions=nope", "model.numbers=digits", "eval.n_valid=3",
               "model.newlines=joined", "variant=no-all")
    results = run_job(cfg)
    assert results["valid_n_episodes"] == 3 and results["n_episodes"] == 3
    (job,) = _job_runs(cfg)
    ids = {step: job.data.tags[step_run_tag(step)] for step in ("data-build", "finetune", "eval")}
    client = mlflow.MlflowClient(cfg.tracking.uri)
    conversations = Path(mlflow.artifacts.download_artifacts(run_id=ids["data-build"], tracking_uri=cfg.tracking.uri,
                                                             artifact_path="conversations/train.jsonl")).read_text()
    assert "Step:" in conversations and "Step 1:" not in conversations
    assert "untrained_words" in client.get_run(ids["data-build"]).data.metrics
    model_dir = mlflow.artifacts.download_artifacts(run_id=ids["finetune"], artifact_path="model",
                                                    tracking_uri=cfg.tracking.uri)
    assert json.loads((Path(model_dir) / "config.json").read_text())["no_rope_layers"] == [0, 0]
    from pipeline.lm.models import load_tokenizer

    assert load_tokenizer(model_dir).tokenize("Step 12:\n(0, 1)\nup") == ["Step", " ", "1", "2", ":\n", "(0, 1)\n",
                                                                         "up"]
    valid = [json.loads(line) for line in open(mlflow.artifacts.download_artifacts(
        run_id=ids["eval"], artifact_path="episodes_valid.jsonl", tracking_uri=cfg.tracking.uri))]
    test = [json.loads(line) for line in open(mlflow.artifacts.download_artifacts(
        run_id=ids["eval"], artifact_path=EPISODES_ARTIFACT, tracking_uri=cfg.tracking.uri))]
    assert len(valid) == 3 and [r["world_index"] for r in valid] == [0, 1, 2]
    assert [(r["size_x"], r["size_y"], r["optimal_length"]) for r in valid] != \
        [(r["size_x"], r["size_y"], r["optimal_length"]) for r in test]
    assert "| validation " in capsys.readouterr().out


# The paper template with Meta-Llama-3-8B's real tokenizer on a tiny random Llama: the code path of
# model=llama3_8b train=paper at toy size. A context of 448 tokens cuts the longest toy maps (up to ~500).
LLAMA3_JOB = ["data=toy", "train=toy", "eval=toy", "model=hf", "model/chat_format=paper", "model.max_length=448",
              "train.long_conversations=truncate", "train.max_steps=2", "train.per_device_batch_size=2",
              "eval.n_worlds=2", "eval.max_new_tokens=32"]


@pytest.mark.slow
def test_a_llama_with_the_real_llama3_tokenizer_trains_and_decodes_the_paper_template(tmp_path, tiny_llama3_dir,
                                                                                     caplog):
    from pipeline.lm.models import PAD_TOKEN, load_chat_format, load_model, load_tokenizer

    cfg = compose_job(tmp_path, f"model.path={tiny_llama3_dir}", *LLAMA3_JOB, toy=False)
    with caplog.at_level("INFO", logger="pipeline.lm"):
        results = run_job(cfg)
    assert results["n_episodes"] == 2
    (job,) = _job_runs(cfg)
    finetune = mlflow.MlflowClient(cfg.tracking.uri).get_run(job.data.tags[step_run_tag("finetune")])
    # 1. The tokenizer had no pad token: "<pad>" was added and the model grew a row for it.
    assert finetune.data.params["model.vocab_size"] == "128257"
    assert "the tokenizer has no pad token: added <pad> (id 128256)" in caplog.text
    model_dir = Path(mlflow.artifacts.download_artifacts(run_id=finetune.info.run_id, artifact_path="model",
                                                         tracking_uri=cfg.tracking.uri))
    tokenizer = load_tokenizer(model_dir)
    assert (tokenizer.pad_token, tokenizer.pad_token_id) == (PAD_TOKEN, 128256)
    assert load_model(model_dir).get_input_embeddings().num_embeddings == 128257
    assert load_chat_format(model_dir).first_human_prefix == "[INST] "
    # 3. The longest conversations were cut to the context and trained on, as the paper's code does.
    metrics = finetune.data.metrics
    assert metrics["truncated_conversations"] > 0 and metrics["dropped_conversations"] == 0
    said = re.findall(r"(training|held-out): \d+ of \d+ conversations are longer than max_length=448 tokens "
                      r"\(train.long_conversations=truncate\): (\d+) truncated to their first 448 tokens", caplog.text)
    assert [part for part, _ in said] == ["training", "held-out"][:len(said)]
    assert sum(int(n) for _, n in said) == metrics["truncated_conversations"]
    assert finetune.data.params["train.long_conversations"] == "truncate"
