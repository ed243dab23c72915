"""`python -m pipeline.report.study`: compare recipes in one store, the way a lever study reads.

The report proper (`pipeline.report.build`) keeps one job per cell (mode, direction, variant, seed); a study
runs the *same* cell under several recipes. Here every finished job is a row, named by the config values in
which the store's jobs differ (its recipe), with success on the validation worlds (``eval.n_valid``: what
recipes are chosen on) and on the test worlds, each split into interpolated and extrapolated worlds with 95%
Wilson intervals, and McNemar's exact test against a reference row on the same worlds.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from pipeline.report.cli import add_store_arguments, store_of
from pipeline.report.load import ReportError, finished_job_runs, open_experiment
from pipeline.report.stats import mcnemar, wilson_interval
from pipeline.workflow.tracking import EPISODES_ARTIFACT, VALID_EPISODES_ARTIFACT, step_run_tag

# Config keys that never change what a job measures (where it is stored), left out of a recipe's name.
_IGNORED = ("tracking.", "work_dir", "hydra.", "skip_undefined", "data.workers")
SPLITS = ("valid", "test")
SUBSETS = ("all", "interp", "extrap")


@dataclass
class Row:
    """One finished job: its recipe (the differing config values) and its episodes on each split."""

    run_id: str
    recipe: dict[str, object]
    episodes: dict[str, list[dict]]   # split -> records in world order (empty: not evaluated)

    def outcomes(self, split: str, subset: str) -> list[bool]:
        records = self.episodes.get(split, [])
        if subset != "all":
            records = [r for r in records if bool(r["interpolated"]) == (subset == "interp")]
        return [bool(r["success"]) for r in records]


def _flat(config: dict, prefix: str = "") -> dict[str, object]:
    flat = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flat(value, name + "."))
        else:
            flat[name] = json.dumps(value) if isinstance(value, list) else value
    return flat


def _schema_defaults() -> dict[str, object]:
    """The job config's defaults, flattened: a key a job's config predates had its default."""
    from omegaconf import OmegaConf

    from pipeline.workflow.config import RunConfig

    return _flat(OmegaConf.to_container(OmegaConf.structured(RunConfig), enum_to_str=True))


def _latest_per_recipe(configs: list[dict]) -> list[int]:
    """Indices of the latest run of each distinct config (a rerun that only re-evaluated supersedes its first)."""
    latest: dict[str, int] = {}
    for i, config in enumerate(configs):
        latest[json.dumps({k: v for k, v in config.items() if not k.startswith(_IGNORED)}, sort_keys=True,
                          default=str)] = i
    return sorted(latest.values())


def load_rows(tracking_uri: str, experiment: str) -> list[Row]:
    """The latest FINISHED job of each distinct config in the store, oldest first, with the config values in
    which the jobs differ (a key a job's config predates counts as its default)."""
    client, found = open_experiment(tracking_uri, experiment)
    runs = finished_job_runs(client, found.experiment_id)
    defaults = _schema_defaults()
    with tempfile.TemporaryDirectory() as scratch:
        configs = []
        for run in runs:
            folder = Path(scratch) / run.info.run_id
            folder.mkdir()
            config = json.loads(Path(client.download_artifacts(run.info.run_id, "config.json", str(folder))).read_text())
            configs.append({**defaults, **_flat(config)})
        kept = _latest_per_recipe(configs)
        runs, configs = [runs[i] for i in kept], [configs[i] for i in kept]
        episodes = []
        for run in runs:
            eval_id = run.data.tags.get(step_run_tag("eval"))
            names = {artifact.path for artifact in client.list_artifacts(eval_id)} if eval_id else set()
            folder = Path(scratch) / run.info.run_id
            episodes.append({split: _records(client, eval_id, name, folder) if name in names else []
                             for split, name in zip(SPLITS, (VALID_EPISODES_ARTIFACT, EPISODES_ARTIFACT))})
    keys = sorted({key for config in configs for key in config if not key.startswith(_IGNORED)})
    differing = [key for key in keys if len({json.dumps(c.get(key), default=str) for c in configs}) > 1]
    return [Row(run.info.run_id, {key: config.get(key) for key in differing}, found)
            for run, config, found in zip(runs, configs, episodes)]


def _records(client, run_id: str, name: str, folder: Path) -> list[dict]:
    path = client.download_artifacts(run_id, name, str(folder))
    records = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    return sorted(records, key=lambda r: r["world_index"])


def _rate(outcomes: list[bool]) -> str:
    if not outcomes:
        return "-"
    k, n = sum(outcomes), len(outcomes)
    low, high = wilson_interval(k, n)
    return f"{k / n:.3f} [{low:.3f}, {high:.3f}] ({k}/{n})"


def _versus(row: Row, reference: Row, split: str, subset: str) -> str:
    a, b = row.outcomes(split, subset), reference.outcomes(split, subset)
    if row is reference or not a or len(a) != len(b):
        return "-"
    test = mcnemar(a, b)
    return f"+{test.only_a} / -{test.only_b}, p {test.p_value:.2g}"


def _recipe(row: Row) -> str:
    return ", ".join(f"{key}={value}" for key, value in row.recipe.items()) or "(one recipe)"


def study_table(rows: list[Row], reference: int = 0) -> str:
    """The study as Markdown: a row per job, rates with Wilson intervals, McNemar against row ``reference``
    on the extrapolated worlds of each split (worlds it solves that the reference does not / the other way)."""
    if not rows:
        return "No finished job in this store.\n"
    if not 0 <= reference < len(rows):
        raise ReportError(f"--reference {reference}: allowed 0..{len(rows) - 1} (a row of the study)")
    base = rows[reference]
    header = ["#", "recipe", *(f"{split} {subset}" for split in SPLITS for subset in SUBSETS),
              *(f"{split} extrap vs #{reference}" for split in SPLITS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for i, row in enumerate(rows):
        cells = [str(i), _recipe(row), *(_rate(row.outcomes(split, subset)) for split in SPLITS for subset in SUBSETS),
                 *(_versus(row, base, split, "extrap") for split in SPLITS)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.report.study", description=__doc__.split("\n")[0])
    add_store_arguments(parser)
    parser.add_argument("--reference", type=int, default=0, help="the row McNemar's tests compare against")
    parser.add_argument("--out", help="also write the table to this Markdown file")
    args = parser.parse_intermixed_args(argv)  # tracking.root=DIR may follow the options
    tracking_uri, experiment = store_of(parser, args)
    try:
        table = study_table(load_rows(tracking_uri, experiment), args.reference)
    except ReportError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(table, end="")
    if args.out:
        Path(args.out).write_text(table, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
