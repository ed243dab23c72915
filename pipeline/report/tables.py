"""How the report's tables are computed, in long form: Tables 1, 3, 7, 8 (and ours) by subset, the paired
tests, the graded optimal setting, where maps go wrong, the reachable outcomes, the jobs used. Which tables the
report has, with their titles and rows, is declared in :mod:`pipeline.report.registry`.

Every rate is over episodes; an episode that could not run (``outcome == "error"``) counts as a failure.
Several seeds in one cell: the rate is the mean of the per-seed rates, the interval the 95% Wilson interval
of all episodes pooled over seeds, and the per-seed range is printed beside it.
"""

from __future__ import annotations

import math
from typing import Callable, Iterable

import pandas as pd

from pipeline.core.map_errors import STEP_BUCKETS
from pipeline.core.variants import DIRECTIONS, MAP_VARIANTS, MODES, PAPER_ROWS, REFERENCE, VARIANTS
from pipeline.report.load import Job, _index, _seed_key
from pipeline.report.paper import paper_success
from pipeline.report.stats import mcnemar, seeded_rate

MISSING = "not run"

# Every table is also split by these subsets of the test worlds (name -> episode filter).
SUBSETS: dict[str, Callable[[pd.DataFrame], pd.Series]] = {
    "all": lambda e: pd.Series(True, index=e.index),
    "up/right only": lambda e: e["up_right_only"] == True,  # noqa: E712 (nullable column)
    "needs down/left": lambda e: e["up_right_only"] == False,  # noqa: E712
    "interpolated": lambda e: e["interpolated"] == True,  # noqa: E712
    "extrapolated": lambda e: e["interpolated"] == False,  # noqa: E712
}


def directions_of(episodes: pd.DataFrame) -> list[str]:
    """fwd and bwd, then any other direction tag found in the data."""
    extra = sorted(set(episodes["direction"].dropna()) - set(DIRECTIONS))
    return [*DIRECTIONS, *extra]


class Cells:
    """The episodes grouped by job cell (mode, direction, variant); a cell that did not run is empty."""

    def __init__(self, episodes: pd.DataFrame) -> None:
        self.episodes = episodes
        self.directions = directions_of(episodes)
        self._groups = dict(iter(episodes.groupby(["mode", "direction", "variant"], sort=False)))
        self._empty = episodes.iloc[0:0]

    def __call__(self, mode: str, direction: str, variant: str) -> pd.DataFrame:
        return self._groups.get((mode, direction, variant), self._empty)

    def present(self, mode: str) -> list[tuple[str, str]]:
        """The (direction, variant) cells that ran in ``mode``, in table order."""
        order = {v: i for i, v in enumerate(VARIANTS)}
        return sorted(((d, v) for m, d, v in self._groups if m == mode),
                      key=lambda dv: (_index(DIRECTIONS, dv[0]), dv[0], order.get(dv[1], 99), dv[1]))


def _subset(frame: pd.DataFrame, subset: str) -> pd.DataFrame:
    return frame[SUBSETS[subset](frame).fillna(False).astype(bool)]


def _seed_mean(frame: pd.DataFrame, column: str) -> float:
    """Mean over seeds of the per-seed mean of ``column`` (nulls skipped); nan without values."""
    values = frame.groupby("seed")[column].apply(
        lambda s: pd.to_numeric(s, errors="coerce").astype(float).mean())
    values = values.dropna()
    return float(values.mean()) if len(values) else math.nan


def rate_stats(frame: pd.DataFrame, ran: bool) -> dict:
    """Success statistics of one cell's episodes: status, counts, rate, Wilson interval, seed spread."""
    if not ran:
        return {"status": MISSING, "n_seeds": 0, "n": 0, "successes": 0, "rate": math.nan,
                "ci_low": math.nan, "ci_high": math.nan, "seed_min": math.nan,
                "seed_max": math.nan, "seed_sd": math.nan}
    rate = seeded_rate([(int(g["success"].sum()), len(g)) for _, g in frame.groupby("seed")])
    return {"status": "ok" if rate.n else "n=0", "n_seeds": rate.n_seeds, "n": rate.n,
            "successes": rate.successes, "rate": rate.rate, "ci_low": rate.ci_low,
            "ci_high": rate.ci_high, "seed_min": rate.seed_min, "seed_max": rate.seed_max,
            "seed_sd": rate.seed_sd}


def success_table(cells: Cells, variants: Iterable[str]) -> pd.DataFrame:
    """Long table: one row per subset x mode x direction x variant with our rate and the paper's."""
    rows = []
    for subset in SUBSETS:
        for mode in MODES:
            for direction in cells.directions:
                for variant in variants:
                    cell = cells(mode, direction, variant)
                    rows.append({
                        "subset": subset, "mode": mode, "direction": direction, "variant": variant,
                        "paper_row": PAPER_ROWS.get(variant, variant),
                        **rate_stats(_subset(cell, subset), ran=len(cell) > 0),
                        "paper": paper_success(mode, variant, direction) if subset == "all"
                        else math.nan,
                    })
    return pd.DataFrame(rows)


def table3(cells: Cells) -> pd.DataFrame:
    """Table 3 (reachable): the paper's cognitive map (BWD marking-deadend), our best map, and DFS."""
    entries = [("cognitive map (BWD MARKING deadend)", "bwd", REFERENCE)]
    ranked = [(rate_stats(cells("reachable", d, v), True)["rate"], d, v)
              for d in cells.directions for v in MAP_VARIANTS
              if len(cells("reachable", d, v))]
    if ranked:
        _, d, v = max(ranked)
        if (d, v) != ("bwd", REFERENCE):
            entries.append((f"best cognitive map of ours ({d.upper()} {PAPER_ROWS[v]})", d, v))
    dfs_directions = [d for d in cells.directions if len(cells("reachable", d, "dfs"))]
    entries += [(f"DFS exploration ({d.upper()} run)", d, "dfs") for d in dfs_directions] or [
        ("DFS exploration", "bwd", "dfs")]
    rows = []
    for subset in SUBSETS:
        for label, direction, variant in entries:
            cell = cells("reachable", direction, variant)
            part = _subset(cell, subset)
            won = part[part["success"]]
            rows.append({
                "subset": subset, "row": label, "mode": "reachable", "direction": direction,
                "variant": variant, **rate_stats(part, ran=len(cell) > 0),
                "moves_over_optimal": _seed_mean(
                    won.assign(ratio=won["n_moves"] / won["optimal_length"]), "ratio")
                if len(won) else math.nan,
                "paper": paper_success("reachable", variant, direction) if subset == "all"
                else math.nan,
            })
    return pd.DataFrame(rows)


def _paired(cells: Cells, mode: str, direction: str, variant: str, reference: str,
            subset: str) -> tuple[pd.DataFrame, list[str]]:
    """Outcomes of ``variant`` and ``reference`` on shared (seed, world) pairs.

    Shared seeds are paired seed by seed; with no seed in common, the lowest seed of each is paired.
    """
    a = _subset(cells(mode, direction, variant), subset)
    b = _subset(cells(mode, direction, reference), subset)
    seeds = sorted(set(a["seed"]) & set(b["seed"]), key=_seed_key)
    if seeds:
        a, b = a[a["seed"].isin(seeds)], b[b["seed"].isin(seeds)]
    elif len(a) and len(b):
        sa, sb = min(set(a["seed"]), key=_seed_key), min(set(b["seed"]), key=_seed_key)
        a, b = a[a["seed"] == sa].assign(seed=sb), b[b["seed"] == sb]
        seeds = [f"{sa}~{sb}"]
    keys = ["seed", "world_index"]
    merged = a[[*keys, "success"]].drop_duplicates(keys).merge(
        b[[*keys, "success"]].drop_duplicates(keys), on=keys, suffixes=("_a", "_b"))
    return merged, seeds


def mcnemar_table(cells: Cells) -> pd.DataFrame:
    """Each variant against its direction's marking-deadend (same mode), paired on shared test worlds."""
    rows = []
    for subset in SUBSETS:
        for mode in MODES:
            for direction in cells.directions:
                if not len(cells(mode, direction, REFERENCE)):
                    continue
                for variant in VARIANTS:
                    if variant == REFERENCE or not len(cells(mode, direction, variant)):
                        continue
                    pairs, seeds = _paired(cells, mode, direction, variant, REFERENCE, subset)
                    test = mcnemar(pairs["success_a"].tolist(), pairs["success_b"].tolist())
                    n = test.n_pairs
                    rows.append({
                        "subset": subset, "mode": mode, "direction": direction, "variant": variant,
                        "reference": REFERENCE, "seeds": ",".join(map(str, seeds)),
                        "n_pairs": n,
                        "rate_variant": (test.both + test.only_a) / n if n else math.nan,
                        "rate_reference": (test.both + test.only_b) / n if n else math.nan,
                        "only_variant": test.only_a, "only_reference": test.only_b,
                        "both": test.both, "neither": test.neither,
                        "p_value": test.p_value if n else math.nan,
                    })
    return pd.DataFrame(rows, columns=[
        "subset", "mode", "direction", "variant", "reference", "seeds", "n_pairs", "rate_variant",
        "rate_reference", "only_variant", "only_reference", "both", "neither", "p_value"])


def graded_table(cells: Cells) -> pd.DataFrame:
    """Optimal setting, graded (docs/spec.md §4): parsed, valid, reaches goal, success, map exact, first map error."""
    rows = []
    for subset in SUBSETS:
        for direction, variant in cells.present("optimal"):
            part = _subset(cells("optimal", direction, variant), subset)
            wrong = pd.to_numeric(part.loc[part["map_exact"] == False, "map_first_error"],  # noqa: E712
                                  errors="coerce").dropna()
            rows.append({
                "subset": subset, "direction": direction, "variant": variant, "n": len(part),
                **{f"rate_{c}": _seed_mean(part, c)
                   for c in ("parsed", "valid", "reaches_goal", "success", "map_exact")},
                "n_map_wrong": int((part["map_exact"] == False).sum()),  # noqa: E712
                "first_error_q1": wrong.quantile(0.25) if len(wrong) else math.nan,
                "first_error_median": wrong.median() if len(wrong) else math.nan,
                "first_error_q3": wrong.quantile(0.75) if len(wrong) else math.nan,
            })
    return pd.DataFrame(rows, columns=[
        "subset", "direction", "variant", "n", "rate_parsed", "rate_valid", "rate_reaches_goal",
        "rate_success", "rate_map_exact", "n_map_wrong", "first_error_q1", "first_error_median",
        "first_error_q3"])


MAP_ERROR_SUBSETS = ("all", "interpolated", "extrapolated")


def map_errors_table(cells: Cells) -> pd.DataFrame:
    """Optimal setting: the failing episodes of each map job by the kind of their first wrong line
    (map_errors.category), split by BFS step and by whether the state being expanded was the first on its
    frontier."""
    rows = []
    for subset in MAP_ERROR_SUBSETS:
        for direction, variant in cells.present("optimal"):
            part = _subset(cells("optimal", direction, variant), subset)
            failed = part[~part["success"] & part["wrong_category"].notna()]
            for name, block in failed.groupby("wrong_category", sort=True):
                steps = block["wrong_step"].value_counts()
                rows.append({
                    "subset": subset, "direction": direction, "variant": variant, "category": name,
                    "n": len(block), "share": len(block) / len(failed),
                    **{bucket: int(steps.get(bucket, 0)) for bucket in STEP_BUCKETS},
                    "later_frontier_state": int((block["wrong_state"] > 0).sum()),
                })
    return pd.DataFrame(rows, columns=["subset", "direction", "variant", "category", "n", "share",
                                       *STEP_BUCKETS, "later_frontier_state"])


def map_errors_by_step_table(curve_episodes: pd.DataFrame) -> pd.DataFrame:
    """How the kinds of first wrong lines move with training: for each job whose checkpoints were evaluated
    (optimal setting), per checkpoint step and subset, the failing episodes by category."""
    columns = ["subset", "direction", "variant", "seed", "step", "n_episodes", "success_rate", "category", "n",
               "share"]
    if curve_episodes.empty:
        return pd.DataFrame(columns=columns)
    rows = []
    optimal = curve_episodes[curve_episodes["mode"] == "optimal"]
    for subset in MAP_ERROR_SUBSETS:
        part = _subset(optimal, subset)
        for (direction, variant, seed, step), block in part.groupby(["direction", "variant", "seed", "step"],
                                                                    sort=True):
            failed = block[~block["success"] & block["wrong_category"].notna()]
            for name, group in failed.groupby("wrong_category", sort=True):
                rows.append({"subset": subset, "direction": direction, "variant": variant, "seed": seed,
                             "step": int(step), "n_episodes": len(block), "success_rate": block["success"].mean(),
                             "category": name, "n": len(group), "share": len(group) / len(failed)})
    return pd.DataFrame(rows, columns=columns)


REACHABLE_OUTCOMES = ("success", "deadend", "max_step", "invalid", "error")


def outcomes_table(cells: Cells) -> pd.DataFrame:
    """Reachable setting: the rate of each outcome per job cell, and moves over optimal on successes."""
    rows = []
    for subset in SUBSETS:
        for direction, variant in cells.present("reachable"):
            part = _subset(cells("reachable", direction, variant), subset)
            won = part[part["success"]]
            rows.append({
                "subset": subset, "direction": direction, "variant": variant, "n": len(part),
                **{f"rate_{o}": _seed_mean(part.assign(hit=part["outcome"] == o), "hit")
                   for o in REACHABLE_OUTCOMES},
                "moves_over_optimal": _seed_mean(
                    won.assign(ratio=won["n_moves"] / won["optimal_length"]), "ratio")
                if len(won) else math.nan,
            })
    return pd.DataFrame(rows, columns=[
        "subset", "direction", "variant", "n", *(f"rate_{o}" for o in REACHABLE_OUTCOMES),
        "moves_over_optimal"])


def jobs_table(jobs: list[Job]) -> pd.DataFrame:
    """The job runs the report used, with their step runs."""
    return pd.DataFrame([{"mode": j.mode, "direction": j.direction, "variant": j.variant,
                          "seed": j.seed, "paper_row": j.paper_row, "job_run_id": j.run_id,
                          "eval_run_id": j.eval_run_id, "finetune_run_id": j.finetune_run_id}
                         for j in jobs],
                        columns=["mode", "direction", "variant", "seed", "paper_row", "job_run_id",
                                 "eval_run_id", "finetune_run_id"])
