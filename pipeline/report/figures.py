"""The report's figures (PNG): size heatmaps (paper Figures 6-15), moves vs optimal length (Figure 4) and
rapid adaptation (Figure 3). Inputs are the episode, curve and loss frames of :mod:`pipeline.report.build.build`.

Figures are drawn with matplotlib's object API (``Figure`` renders with Agg), so no pyplot state and no
display are involved.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from matplotlib.ticker import MaxNLocator

from pipeline.core.variants import PAPER_ROWS, VARIANTS
from pipeline.workflow.tracking import TRAIN_MAX_TAGS

HEATMAP_METRICS = {  # name -> (title, outcome it counts or None for success, modes it applies to)
    "success": ("SUCCESS rate", None, ("optimal", "reachable")),
    "deadend": ("DEADEND rate", "deadend", ("reachable",)),
    "max_step": ("MAX STEP rate", "max_step", ("reachable",)),
    "invalid": ("INVALID rate", "invalid", ("reachable",)),
}
DPI = 110


def _variants(frame: pd.DataFrame) -> list[str]:
    present = set(frame["variant"])
    return [v for v in VARIANTS if v in present] + sorted(present - set(VARIANTS))


def _direction_order(item: tuple[str, pd.DataFrame]) -> tuple[int, str]:
    return ({"fwd": 0, "bwd": 1}.get(item[0], 2), item[0])


def train_box(episodes: pd.DataFrame) -> tuple[int, int] | None:
    """The train maximum (X, Y): from the jobs' ``train_max_x/y`` tags when they all carry the same one, else
    inferred as the largest sizes of the episodes marked interpolated (jobs logged before the tags existed)."""
    if set(TRAIN_MAX_TAGS) <= set(episodes.columns):
        boxes = set(zip(*(episodes[column] for column in TRAIN_MAX_TAGS)))
        if len(boxes) == 1 and not any(pd.isna(v) for v in next(iter(boxes))):
            x, y = next(iter(boxes))
            return int(x), int(y)
    interp = episodes[episodes["interpolated"] == True]  # noqa: E712 (nullable column)
    if interp.empty:
        return None
    return int(interp["size_x"].max()), int(interp["size_y"].max())


def size_grid(frame: pd.DataFrame, values: pd.Series, sizes: range) -> np.ndarray:
    """Mean of ``values`` per (Y, X) size over ``sizes`` x ``sizes``; nan where no world has that size."""
    table = values.groupby([frame["size_y"], frame["size_x"]]).mean()
    grid = np.full((len(sizes), len(sizes)), np.nan)
    for (y, x), value in table.items():
        if int(y) in sizes and int(x) in sizes:
            grid[int(y) - sizes.start, int(x) - sizes.start] = value
    return grid


def size_heatmaps(episodes: pd.DataFrame, out: Path) -> list[Path]:
    """One figure per (mode, direction, metric): a panel per variant, success (or outcome) rate by size.

    Seeds are pooled. Each panel's train boundary (:func:`train_box`) is drawn as a red box. Each size with
    test worlds carries its number of episodes (``n``); a size no test world has is grey and marked ``-``,
    so it cannot be read as a rate of 0. All panels share the 0-1 colour scale.
    """
    if episodes.empty:
        return []
    out.mkdir(parents=True, exist_ok=True)
    sizes = range(int(min(episodes["size_x"].min(), episodes["size_y"].min(), 2)),
                  int(max(episodes["size_x"].max(), episodes["size_y"].max())) + 1)
    paths = []
    for mode, by_mode in episodes.groupby("mode", sort=True):
        for direction, block in sorted(by_mode.groupby("direction"), key=_direction_order):
            for metric, (title, outcome, modes) in HEATMAP_METRICS.items():
                if mode not in modes:
                    continue
                variants = _variants(block)
                ncols = min(4, len(variants))
                nrows = math.ceil(len(variants) / ncols)
                fig = Figure(figsize=(3.4 * ncols + 0.8, 3.2 * nrows + 0.4), layout="constrained")
                axes = fig.subplots(nrows, ncols, squeeze=False)
                image = None
                for ax, variant in zip(axes.flat, variants):
                    cell = block[block["variant"] == variant]
                    hit = cell["success"] if outcome is None else cell["outcome"] == outcome
                    box = train_box(cell)
                    grid = size_grid(cell, hit.astype(float), sizes)
                    image = ax.imshow(np.ma.masked_invalid(grid), origin="lower", vmin=0, vmax=1,
                                      cmap="viridis",
                                      extent=(sizes.start - 0.5, sizes.stop - 0.5,
                                              sizes.start - 0.5, sizes.stop - 0.5))
                    ax.set_facecolor("0.85")
                    counts = cell.groupby(["size_y", "size_x"]).size()
                    small = len(sizes) > 12  # the paper's 19 x 19 sizes: counts would not fit
                    for y in sizes:
                        for x in sizes:
                            n = int(counts.get((y, x), 0))
                            if n == 0:
                                ax.text(x, y, "-", ha="center", va="center", fontsize=8, color="0.3")
                            elif not small:
                                value = grid[y - sizes.start, x - sizes.start]
                                ax.text(x, y, str(n), ha="center", va="center", fontsize=7,
                                        color="black" if value > 0.6 else "white")
                    if box is not None:
                        ax.add_patch(Rectangle((sizes.start - 0.5, sizes.start - 0.5),
                                               box[0] - sizes.start + 1, box[1] - sizes.start + 1,
                                               fill=False, edgecolor="red", linewidth=1.5))
                    ax.set_title(f"{PAPER_ROWS.get(variant, variant)} (n={len(cell)})", fontsize=9)
                    ax.set_xlabel("X")
                    ax.set_ylabel("Y")
                    # Sizes are whole cells: integer ticks only.
                    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
                    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
                for ax in list(axes.flat)[len(variants):]:
                    ax.set_axis_off()
                fig.colorbar(image, ax=axes, shrink=0.8, label=title)
                fig.suptitle(f"{title} by world size: {mode}, {direction.upper()}\nnumber: test worlds of that "
                             "size; -: none;\nred box: the training sizes", fontsize=9)
                path = out / f"heatmap_{mode}_{direction}_{metric}.png"
                fig.savefig(path, dpi=DPI)
                paths.append(path)
    return paths


def _fit(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least-squares quadratic (linear with fewer than 3 distinct lengths) as polyfit coefficients."""
    degree = 2 if len(np.unique(x)) >= 3 else 1 if len(np.unique(x)) >= 2 else 0
    return np.polyfit(x, y, degree)


def _poly_text(coef: np.ndarray) -> str:
    """``1.00n² + 0.50n - 2.00`` (two decimals: enough to tell n² from n growth)."""
    names = {0: "", 1: "n", 2: "n²"}
    degree = len(coef) - 1
    terms = [f"{abs(c) + 0.0:.2f}{names[degree - i]}" for i, c in enumerate(coef)]
    text = ("-" if coef[0] < 0 and round(coef[0], 2) else "") + terms[0]
    for c, term in zip(coef[1:], terms[1:]):
        text += f" {'-' if c < 0 and round(c, 2) else '+'} {term}"
    return text


def moves_vs_optimal(episodes: pd.DataFrame, out: Path,
                     map_cell: tuple[str, str] | None) -> tuple[Path | None, pd.DataFrame]:
    """Figure 4: moves taken against optimal length on successful reachable episodes, DFS vs the map.

    ``map_cell`` is the (direction, variant) of the cognitive map shown. Each series gets a least-squares
    quadratic (the paper: DFS grows like n², the map like n); the fits are returned as a table.
    """
    reach = episodes[(episodes["mode"] == "reachable") & episodes["success"]]
    series = []
    for direction in sorted(set(reach.loc[reach["variant"] == "dfs", "direction"])):
        series.append((f"DFS ({direction.upper()} run)", reach[(reach["variant"] == "dfs")
                                                               & (reach["direction"] == direction)]))
    if map_cell is not None:
        direction, variant = map_cell
        series.append((f"cognitive map: {direction.upper()} {PAPER_ROWS.get(variant, variant)}",
                       reach[(reach["variant"] == variant) & (reach["direction"] == direction)]))
    series = [(label, s.dropna(subset=["optimal_length", "n_moves"])) for label, s in series]
    series = [(label, s) for label, s in series if len(s)]
    columns = ["series", "n_episodes", "coefficients", "fit", "mean_moves_over_optimal"]
    if not series:
        return None, pd.DataFrame(columns=columns)
    out.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(6.4, 4.8), layout="constrained")
    ax = fig.subplots()
    rng = np.random.default_rng(0)  # jitter only, so overlapping integer points stay visible
    rows, top = [], 0.0
    for i, (label, s) in enumerate(series):
        x = s["optimal_length"].to_numpy(float)
        y = s["n_moves"].to_numpy(float)
        colour = f"C{i}"
        ax.scatter(x + rng.uniform(-0.2, 0.2, len(x)), y, s=8, alpha=0.35, color=colour)
        coef = _fit(x, y)
        grid = np.linspace(x.min(), x.max(), 100)
        ax.plot(grid, np.polyval(coef, grid), color=colour, label=f"{label}: {_poly_text(coef)}")
        rows.append({"series": label, "n_episodes": len(s),
                     "coefficients": " ".join(f"{c:.6g}" for c in coef), "fit": _poly_text(coef),
                     "mean_moves_over_optimal": float(np.mean(y / np.maximum(x, 1)))})
        top = max(top, x.max())
    ax.plot([0, top], [0, top], "k--", linewidth=1, label="optimal (moves = n)")
    ax.set_xlabel("optimal length n")
    ax.set_ylabel("moves taken")
    ax.set_title("Successful reachable episodes: moves vs optimal length")
    ax.legend(fontsize=8)
    path = out / "fig4_moves_vs_optimal.png"
    fig.savefig(path, dpi=DPI)
    return path, pd.DataFrame(rows, columns=columns)


def _label(row: pd.Series | tuple, with_mode: bool = True) -> str:
    mode, direction, variant = row
    text = f"{PAPER_ROWS.get(variant, variant)} {direction.upper()}"
    return f"{text}, {mode}" if with_mode else text


def rapid_adaptation(curves: pd.DataFrame, losses: pd.DataFrame, out: Path,
                     keep=lambda direction, variant: True) -> Path | None:
    """Figure 3: checkpoint success rate and training loss against training step (means over seeds).

    ``keep(direction, variant)`` selects the jobs shown.
    """
    def select(frame: pd.DataFrame) -> pd.DataFrame:
        if frame.empty:
            return frame
        return frame[[keep(d, v) for d, v in zip(frame["direction"], frame["variant"])]]

    curves, losses = select(curves), select(losses)
    if curves.empty and losses.empty:
        return None
    out.mkdir(parents=True, exist_ok=True)
    fig = Figure(figsize=(11, 4.2), layout="constrained")
    left, right = fig.subplots(1, 2)
    for key, block in (curves.groupby(["mode", "direction", "variant"]) if len(curves) else []):
        mean = block.groupby(["seed", "step"])["value"].mean().groupby("step").mean()
        left.plot(mean.index, mean.to_numpy(), marker="o", markersize=3, label=_label(key))
    # One finetune run can serve several jobs (modes): draw it once.
    if len(losses):
        losses = losses.drop_duplicates(["finetune_run_id", "step"])
    for key, block in (losses.groupby(["direction", "variant"]) if len(losses) else []):
        per_run = block.groupby(["finetune_run_id", "step"])["value"].mean()
        for run_id, run in per_run.groupby(level=0):
            modes = ", ".join(sorted(set(block.loc[block["finetune_run_id"] == run_id, "mode"])))
            steps = run.index.get_level_values("step")
            right.plot(steps, run.to_numpy(), linewidth=1,
                       label=f"{_label(('', *key), with_mode=False)} ({modes}, {run_id[:6]})")
    left.set(xlabel="training step", ylabel="success rate (checkpoint subset)", ylim=(-0.02, 1.02),
             title="Success rate during training")
    # The loss falls by orders of magnitude: on a linear scale everything after the first steps is flat.
    right.set(xlabel="training step", ylabel="training loss (log scale)", title="Training loss",
              yscale="log" if len(losses) and (losses["value"] > 0).all() else "linear")
    for ax, frame in ((left, curves), (right, losses)):
        if frame.empty:
            ax.text(0.5, 0.5, "no data logged", ha="center", va="center", transform=ax.transAxes)
        else:
            ax.legend(fontsize=7)
    path = out / "fig3_rapid_adaptation.png"
    fig.savefig(path, dpi=DPI)
    return path


# ---------------------------------------------------------------------------------------------- gallery
GALLERY_PER_OUTCOME = 3
_OUTCOME_COLOURS = {True: "#1a9850", False: "#d73027"}


def gallery_picks(records: list[dict], per_outcome: int = GALLERY_PER_OUTCOME) -> list[dict]:
    """The episodes a gallery shows: the first ``per_outcome`` successes and failures by world index, the
    failures among those that moved at all first (a plan or walk to draw), so the choice is deterministic."""
    ordered = sorted(records, key=lambda r: r["world_index"])
    won = [r for r in ordered if r.get("success")]
    lost = [r for r in ordered if not r.get("success")]
    lost = sorted(lost, key=lambda r: (not r.get("moves"), r["world_index"]))
    return won[:per_outcome] + lost[:per_outcome]


def _walk_cells(world, moves: list[str]) -> list[tuple[int, int]]:
    from pipeline.core.world import step

    cells = [world.start]
    for move in moves:
        try:
            cells.append(step(cells[-1], move))
        except ValueError:
            break
        if not world.is_free(cells[-1]):
            break  # the first move into an obstacle or out of the grid ends the drawing there
    return cells


def draw_world(ax, world, moves: list[str], success: bool, title: str) -> None:
    """A world like the paper's Figure 1: walls, pits, start, goal, the optimal path (dashed) and the
    model's plan or walk over it, green when it succeeded and red when it did not."""
    x0, y0 = world.x0, world.y0
    ax.set_xlim(x0 - 0.5, x0 + world.size_x - 0.5)
    ax.set_ylim(y0 - 0.5, y0 + world.size_y - 0.5)
    ax.set_aspect("equal")
    ax.set_facecolor("white")
    for x, y in world.walls:
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), 1, 1, color="0.25"))
    for x, y in world.pits:
        ax.add_patch(Rectangle((x - 0.5, y - 0.5), 1, 1, color="#fdae61"))
    path = np.array(world.shortest_path())
    ax.plot(path[:, 0], path[:, 1], linestyle="--", color="0.45", linewidth=1.2, zorder=2)
    walk = np.array(_walk_cells(world, moves))
    colour = _OUTCOME_COLOURS[bool(success)]
    ax.plot(walk[:, 0], walk[:, 1], color=colour, linewidth=2.6, alpha=0.8, zorder=3)
    if not success and len(walk):
        ax.plot(walk[-1, 0], walk[-1, 1], marker="x", color=colour, markersize=10, mew=2.5, zorder=4)
    ax.plot(*world.start, marker="o", color="#4575b4", markersize=9, zorder=5)
    ax.plot(*world.goal, marker="*", color="#ffd700", markeredgecolor="k", markersize=14, zorder=5)
    ax.set_xticks(range(x0, x0 + world.size_x))
    ax.set_yticks(range(y0, y0 + world.size_y))
    ax.tick_params(labelsize=6, length=0)
    ax.grid(True, color="0.85", linewidth=0.5)
    for x in np.arange(x0 - 0.5, x0 + world.size_x, 1.0):
        ax.axvline(x, color="0.8", linewidth=0.5, zorder=1)
    for y in np.arange(y0 - 0.5, y0 + world.size_y, 1.0):
        ax.axhline(y, color="0.8", linewidth=0.5, zorder=1)
    ax.set_title(title, fontsize=8, color=colour)


def episode_gallery(cases: list[tuple], label: str, path: Path) -> Path | None:
    """One job's gallery: its picked episodes, successes on the top row and failures below.
    ``cases``: (world, record) pairs from :func:`gallery_picks`."""
    if not cases:
        return None
    won = [c for c in cases if c[1].get("success")]
    lost = [c for c in cases if not c[1].get("success")]
    ncols = max(len(won), len(lost), 1)
    rows = [row for row in (won, lost) if row]
    fig = Figure(figsize=(2.6 * ncols + 0.4, 2.8 * len(rows) + 0.6), layout="constrained")
    axes = fig.subplots(len(rows), ncols, squeeze=False)
    for r, row in enumerate(rows):
        for c in range(ncols):
            ax = axes[r][c]
            if c >= len(row):
                ax.set_axis_off()
                continue
            world, record = row[c]
            outcome = record.get("outcome") or ("success" if record.get("success") else "fail")
            draw_world(ax, world, list(record.get("moves") or []), bool(record.get("success")),
                       f"world {record['world_index']} ({world.size_x}x{world.size_y}): {outcome}")
    fig.suptitle(f"{label}\nwalls dark, pits orange, start blue, goal star; optimal path dashed,\nthe model's "
                 "moves in colour (x: where a failure stopped)", fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return path
