"""`python -m pipeline.inspect RUN_ID [--world N] [--failed] | --labels`: show what a model wrote for a test world.

RUN_ID is a job run or its eval run. For each episode shown: the world and the outcome, the task prompt,
and the model's answer beside the golden one (rebuilt from the world), the first differing line marked; in
the reachable setting, the model's answer of every turn after the observation it answered. With
``--labels``: the job's model graded on every line of every validation world's golden answer (`probe_labels`;
``--split test``: the test worlds').
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from itertools import zip_longest
from pathlib import Path
from typing import Sequence

from pipeline.workflow.data_build import SUMMARY, TEST_WORLDS
from pipeline.core.environment import GridEnv
from pipeline.core.scoring import _as_text, first_difference
from pipeline.core.texts import golden_answer, first_human_text
from pipeline.core.variants import MAP_VARIANTS, VARIANTS
from pipeline.report.cli import add_store_arguments, store_of
from pipeline.workflow.tracking import EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, VALID_EPISODES_ARTIFACT, step_run_tag
from pipeline.core.world import World, load_worlds

WIDTH = 30


class InspectError(RuntimeError):
    """What the user asked for cannot be shown (no such run, world out of range)."""


def side_by_side(produced: str, golden: str) -> list[str]:
    """The two answers line by line, numbered, with ``>>`` on the first line where they differ."""
    ours, theirs = _as_text(produced).split("\n"), golden.split("\n")
    first = first_difference(ours, theirs)
    rows = [f"    {'':>4}  {'model':<{WIDTH}}  golden"]
    for number, (a, b) in enumerate(zip_longest(ours, theirs), 1):
        mark = ">>" if first is not None and number - 1 == first else ("  " if a == b else " ~")
        a = "(ended)" if a is None else a
        rows.append(f"{mark}  {number:>4}  {a[:WIDTH]:<{WIDTH}}  {'(ended)' if b is None else b}")
    verdict = "identical" if first is None else f"first difference at line {first + 1}"
    return [f"answer ({verdict}):", *rows]


def reachable_turns(world: World, moves: Sequence[str], answers: Sequence[str]) -> list[str]:
    """Each observation the model saw and its answer, replayed through the environment."""
    env, lines = GridEnv(world, max_moves=max(len(answers), 1)), []
    env.reset()
    observation = "(the task prompt above)"
    for turn, text in enumerate(answers, 1):
        lines += [f"--- turn {turn}: observation", observation, f"--- turn {turn}: model", _as_text(text)]
        if turn - 1 >= len(moves):
            break
        result = env.step(moves[turn - 1])
        if result.done:
            break
        observation = result.observation
    return lines


def show_episode(record: dict, world: World, direction: str, variant: str, mode: str, steps: str = "numbered",
                 plan: str = "moves") -> str:
    """One episode as text: header, prompt, and the model's answer(s) against the golden one."""
    kind = "interpolated" if record.get("interpolated") else "extrapolated"
    lines = [f"world {record['world_index']} ({world.size_x} x {world.size_y}, {kind}, optimal length "
             f"{record.get('optimal_length')}): {record.get('outcome')}"
             + (f" ({record['error']})" if record.get("error") else ""),
             "--- task prompt", first_human_text(world)]
    answers = record.get("answers") or []
    if mode == "optimal":
        golden = golden_answer(world, direction, variant, "optimal", steps=steps, plan=plan)
        lines += side_by_side(answers[0] if answers else "", golden)
        wrong = record.get("first_wrong_line")
        if wrong:
            where = ", ".join(f"{k} {wrong[k]}" for k in ("section", "line", "step", "state", "neighbour",
                                                              "label_error") if wrong.get(k) is not None)
            lines.append(f"first wrong line: {where}")
    else:
        lines += reachable_turns(world, record.get("moves") or [], answers)
        lines.append(f"moves: {' '.join(record.get('moves') or [])}")
    return "\n".join(lines)


def _runs(client, run_id: str) -> tuple:
    """(job run, eval run) for a job run id or an eval run id."""
    from mlflow.exceptions import MlflowException

    try:
        run = client.get_run(run_id)
    except MlflowException:
        raise InspectError(f"no run {run_id!r} in this store; give a job run id or its eval run id "
                           "(the job's summary line prints the job run id)") from None
    if run.data.tags.get(KIND_TAG) == JOB_KIND:
        job = run
    else:
        found = client.search_runs([run.info.experiment_id],
                                   filter_string=f"tags.`{step_run_tag('eval')}` = '{run_id}'", max_results=1)
        if not found:
            raise InspectError(f"run {run_id!r} is neither a job run nor the eval run of one")
        job = found[0]
    eval_id = job.data.tags.get(step_run_tag("eval"))
    if not eval_id:
        raise InspectError(f"job {job.info.run_id} has no eval run (it did not finish)")
    return job, client.get_run(eval_id)


def inspect_run(tracking_uri: str, run_id: str, world: int | None = None, failed: bool = False,
                limit: int = 3) -> str:
    """The text `python -m pipeline.inspect` prints."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri)
    job, evaluation = _runs(client, run_id)
    tags = job.data.tags
    direction, variant, mode = tags.get("direction", "fwd"), tags.get("variant", ""), tags.get("mode", "optimal")
    if variant not in VARIANTS:
        raise InspectError(f"job {job.info.run_id} has variant {variant!r}; this version knows {', '.join(VARIANTS)}")
    with tempfile.TemporaryDirectory() as scratch:
        data_id = tags[step_run_tag("data-build")]
        worlds = load_worlds(client.download_artifacts(data_id, TEST_WORLDS, scratch))
        summary = json.loads(Path(client.download_artifacts(data_id, SUMMARY, scratch)).read_text())
        path = client.download_artifacts(evaluation.info.run_id, EPISODES_ARTIFACT, scratch)
        records = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    direction = (summary.get("text_spec") or {}).get("direction") or direction
    steps = (summary.get("text_spec") or {}).get("step_headers") or "numbered"
    plan = (summary.get("text_spec") or {}).get("plan_form") or "moves"
    if world is not None:
        chosen = [r for r in records if r["world_index"] == world]
        if not chosen:
            raise InspectError(f"--world {world}: the eval ran worlds 0..{len(records) - 1}")
    else:
        chosen = [r for r in records if not r["success"]] if failed else records
        chosen = chosen[:limit]
    head = (f"job {job.info.run_id} · {direction} {variant} {mode} · eval run {evaluation.info.run_id} · "
            f"{sum(r['success'] for r in records)}/{len(records)} succeeded")
    if not chosen:
        return head + "\nno episode to show" + (" (none failed)" if failed else "")
    return "\n\n".join([head, *(show_episode(r, worlds[r["world_index"]], direction, variant, mode, steps, plan)
                                for r in chosen)]) + "\n"


# The worlds --labels can grade, and how its header names them.
PROBE_SPLITS = {"valid": "validation worlds", "test": "test worlds"}


def probe_labels(tracking_uri: str, run_id: str, limit: int | None = None, split: str = "valid") -> str:
    """The text of ``python -m pipeline.inspect RUN_ID --labels``: the job's model, fed each world's golden
    answer, graded on every line (`pipeline.lm.probe`): the map's labels by what the neighbour is, every line by
    its kind, and the Backtrack's and Plan's moves by their index; inside the training sizes and beyond them; and
    beyond them, the labels of new free cells by how far the cell lies from the grid's low corner.
    ``split``: the validation worlds (the default: a diagnosis that picks the next lever reads them, never the
    test split) or the test worlds."""
    from mlflow.tracking import MlflowClient

    from pipeline.core.map_errors import NEIGHBOURS, PROBE_KINDS, corner_offset, label_cells, line_kinds
    from pipeline.core.texts import prompt_turns
    from pipeline.lm.models import load_chat_format, load_model, load_tokenizer
    from pipeline.lm.probe import labels_predicted

    client = MlflowClient(tracking_uri)
    job, evaluation = _runs(client, run_id)
    tags = job.data.tags
    variant = tags.get("variant", "")
    if variant not in MAP_VARIANTS:
        raise InspectError(f"job {job.info.run_id} has variant {variant!r}: --labels grades a cognitive map's labels")
    if split not in PROBE_SPLITS:
        raise InspectError(f"split {split!r}: one of {', '.join(PROBE_SPLITS)}")
    with tempfile.TemporaryDirectory() as scratch:
        data_id = tags[step_run_tag("data-build")]
        worlds = load_worlds(client.download_artifacts(data_id, TEST_WORLDS, scratch))
        spec = json.loads(Path(client.download_artifacts(data_id, SUMMARY, scratch)).read_text()).get("text_spec") or {}
        episodes = EPISODES_ARTIFACT if split == "test" else VALID_EPISODES_ARTIFACT
        if split == "valid":
            if not any(entry.path == episodes for entry in client.list_artifacts(evaluation.info.run_id)):
                raise InspectError(f"eval run {evaluation.info.run_id} has no validation episodes (eval.n_valid=0); "
                                   "--split test grades the test worlds")
            worlds = _validation_worlds(client, job.info.run_id, data_id, worlds, scratch)
        path = client.download_artifacts(evaluation.info.run_id, episodes, scratch)
        records = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
        if split == "valid":
            _check_same_worlds(worlds, records)
        model_dir = client.download_artifacts(tags[step_run_tag("finetune")], "model", scratch)
        model, tokenizer = load_model(model_dir).eval(), load_tokenizer(model_dir)
        fmt = load_chat_format(model_dir)
    direction, steps = spec.get("direction") or tags.get("direction", "fwd"), spec.get("step_headers") or "numbered"
    plan = spec.get("plan_form") or "moves"
    labels: dict[tuple[bool, str], list[int]] = {}
    lines: dict[tuple[bool, str], list[int]] = {}
    moves: dict[tuple[str, int], list[int]] = {}
    offsets: dict[int, list[int]] = {}  # new free cells beyond the training sizes, by `corner_offset`
    for record in records[:limit]:
        world, inside = worlds[record["world_index"]], record["interpolated"]
        kinds = line_kinds(world, direction, variant, steps, plan)
        answer = golden_answer(world, direction, variant, "optimal", steps=steps, plan=plan)
        graded = labels_predicted(model, tokenizer, fmt, prompt_turns(world, spec.get("prompt", "paper")), answer,
                                  range(len(kinds)))
        for line, kind, cell in label_cells(world, direction, variant, steps, plan):
            _tally(labels, (inside, kind), graded[line])
            if kind == "free" and not inside:
                _tally(offsets, corner_offset(world, cell), graded[line])
        for (kind, move), ok in zip(kinds, graded):
            _tally(lines, (inside, kind), ok)
            if move is not None and not inside:
                _tally(moves, (kind, move), ok)
    head = (f"job {job.info.run_id} · {direction} {variant} · {len(records[:limit])} {PROBE_SPLITS[split]}, each fed "
            "its golden answer: lines predicted (greedy, every token of the line), 95% Wilson interval")
    rows = [head, "", f"{'label of a':<14} {'inside the training sizes':<34} beyond them"]
    rows += [f"{kind:<14} {_rate(labels, (True, kind)):<34} {_rate(labels, (False, kind))}" for kind in NEIGHBOURS]
    rows += ["", f"{'every line':<14} {'inside the training sizes':<34} beyond them"]
    rows += [f"{kind:<14} {_rate(lines, (True, kind)):<34} {_rate(lines, (False, kind))}" for kind in PROBE_KINDS
             if (True, kind) in lines or (False, kind) in lines]
    if moves:
        last = max(move for _, move in moves) + 1
        rows += ["", "beyond the training sizes, by the move's number (1 = first)",
                 f"{'move':<6} {'backtrack move':<34} plan"]
        rows += [f"{move + 1:<6} {_rate(moves, ('backtrack move', move)):<34} {_rate(moves, ('plan', move))}"
                 for move in range(last)]
    if offsets:
        rows += ["", "beyond the training sizes, new free cells by their offset from the grid's low corner",
                 "(the larger of x - x0 and y - y0; inside a training world it is at most its side - 1)",
                 f"{'offset':<6} label"]
        rows += [f"{offset:<6} {_rate(offsets, offset)}" for offset in sorted(offsets)]
    return "\n".join(rows) + "\n"


def _validation_worlds(client, job_id: str, data_id: str, test: list[World], scratch: str) -> list[World]:
    """The job's validation worlds, drawn again as its eval step drew them (`validation_worlds`), from the
    settings in the job's config.json."""
    from omegaconf import OmegaConf

    from pipeline.workflow.data_build import TRAIN_WORLDS, DataSettings, validation_worlds

    config = json.loads(Path(client.download_artifacts(job_id, "config.json", scratch)).read_text())
    data = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(DataSettings), config["data"]))
    train = load_worlds(client.download_artifacts(data_id, TRAIN_WORLDS, scratch))
    return validation_worlds(data, int(config["eval"]["n_valid"]), train, test)


def _check_same_worlds(worlds: list[World], records: list[dict]) -> None:
    """The worlds drawn again are the ones the validation episodes were scored on (sizes and path lengths)."""
    for record in records:
        index = record["world_index"]
        drawn = worlds[index] if index < len(worlds) else None
        if drawn is None or (drawn.size_x, drawn.size_y, len(drawn.optimal_moves())) != (
                record["size_x"], record["size_y"], record["optimal_length"]):
            raise InspectError(f"validation world {index} drawn again differs from the one the eval step scored "
                               "(another version of the generator?); --split test grades the test worlds")


def _tally(counts: dict, key, ok: bool) -> None:
    tally = counts.setdefault(key, [0, 0])
    tally[0], tally[1] = tally[0] + ok, tally[1] + 1


def _rate(counts: dict, key) -> str:
    """``ok / n`` as a rate with its 95% Wilson interval, or - where nothing was graded."""
    from pipeline.report.stats import wilson_interval

    ok, n = counts.get(key, (0, 0))
    if not n:
        return "-"
    low, high = wilson_interval(ok, n)
    return f"{ok / n:.3f} [{low:.3f}, {high:.3f}] ({ok}/{n})"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.inspect", description=__doc__.split("\n")[0])
    parser.add_argument("run_id", help="a job run id (printed by each job) or its eval run id")
    parser.add_argument("--world", type=int, help="the test world's index (default: the first few)")
    parser.add_argument("--failed", action="store_true", help="only episodes that failed")
    parser.add_argument("--limit", type=int, help="how many episodes without --world (default 3; with --labels: "
                                                   "how many worlds, default all)")
    parser.add_argument("--labels", action="store_true",
                        help="grade the model on every line of every validation world's golden answer (a "
                             "teacher-forced probe: labels by neighbour, lines by kind, moves by number)")
    parser.add_argument("--split", choices=list(PROBE_SPLITS), default="valid",
                        help="with --labels: the worlds graded (default valid: recipes are chosen on them)")
    add_store_arguments(parser)
    args = parser.parse_intermixed_args(argv)  # tracking.root=DIR may follow the options
    if args.labels and (args.world is not None or args.failed):
        parser.error("--labels grades every test world's labels; it takes --limit, not --world or --failed")
    tracking_uri, _ = store_of(parser, args)
    try:  # the error exit every command line of the project shares (boilerplate)
        if args.labels:
            print(probe_labels(tracking_uri, args.run_id, args.limit, args.split), end="")
        else:
            limit = 3 if args.limit is None else args.limit
            print(inspect_run(tracking_uri, args.run_id, args.world, args.failed, limit), end="")
    except InspectError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
