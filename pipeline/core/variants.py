"""THE table of what a job can be: directions, modes, the cognitive-map variants and the baselines, with the
paper's row names and the rules that tie them together.

Everything else reads its lists from here: the config's groups and presets (registered in Hydra's ConfigStore
by `pipeline.workflow.config.register_configs`), the texts, scoring, and the report's order of variants (which
variants each report table shows is the report's registry, `pipeline.report.registry`).
Adding a variant is one row in `VARIANT_ROWS`; adding a map switch is one field of `MapSwitches` (plus what
the texts write for it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, NamedTuple

DIRECTIONS: tuple[str, ...] = ("fwd", "bwd")   # BFS from the start or from the goal
MODES: tuple[str, ...] = ("optimal", "reachable")   # single turn, whole plan | multi-turn, one move a turn


class MapSwitches(NamedTuple):
    """The switches a cognitive-map variant is made of: the three of the paper's table, and ``named`` (not
    in the paper), which writes ``From (x, y):`` before the neighbours of each expanded state."""

    all_moves: bool
    marking: bool
    backtrack: bool
    named: bool = False


@dataclass(frozen=True)
class Variant:
    """One row of the table. ``switches`` is None for a baseline (no cognitive map)."""

    name: str
    paper_row: str                    # the row's name in the paper's tables (the job runs' ``paper_row`` tag)
    switches: MapSwitches | None
    direction_free: bool = False      # its texts do not depend on the direction (one dataset serves both)
    reachable_only: bool = False      # defined in the reachable setting only
    in_paper: bool = True

    @property
    def is_map(self) -> bool:
        return self.switches is not None


# The paper's rows, in its order (maps, then baselines). `marking` is meaningless without all-moves: off there.
_PAPER_MAPS = (
    Variant("marking-deadend", "MARKING deadend", MapSwitches(True, True, True)),
    Variant("no-marking", "w.o. MARKING", MapSwitches(True, False, True)),
    Variant("no-backtrack", "w.o. BACKTRACK", MapSwitches(True, True, False)),
    Variant("no-marking-no-backtrack", "w.o. MARKING BACKTRACK", MapSwitches(True, False, False)),
    Variant("no-all", "w.o. ALL", MapSwitches(False, False, True)),
    Variant("no-all-no-backtrack", "w.o. ALL BACKTRACK", MapSwitches(False, False, False)),
)
NAMED_SUFFIX = "-named"
_BASELINES = (
    Variant("none", "NONE", None, direction_free=True),
    Variant("cot", "CoT", None),
    Variant("dfs", "DFS exploration", None, direction_free=True, reachable_only=True),
)
VARIANT_ROWS: tuple[Variant, ...] = (
    *_PAPER_MAPS,
    # Beyond the paper: each map with its expanded states named (`<variant>-named`).
    *(Variant(v.name + NAMED_SUFFIX, f"{v.paper_row}, states named (not in the paper)",
              v.switches._replace(named=True), in_paper=False) for v in _PAPER_MAPS),
    *_BASELINES,
)
BY_NAME: dict[str, Variant] = {v.name: v for v in VARIANT_ROWS}
# Other names a preset answers to (`variant=marking`).
ALIASES: dict[str, str] = {"marking": "marking-deadend", "nomarking": "no-marking"}

# Derived views (the order is the table's: reports and figures list variants in it).
VARIANTS: tuple[str, ...] = tuple(BY_NAME)
MAP_VARIANTS: dict[str, MapSwitches] = {v.name: v.switches for v in VARIANT_ROWS if v.is_map}
PAPER_MAP_VARIANTS: dict[str, MapSwitches] = {v.name: v.switches for v in _PAPER_MAPS}
BASELINES: tuple[str, ...] = tuple(v.name for v in _BASELINES)
PAPER_VARIANTS: tuple[str, ...] = tuple(v.name for v in VARIANT_ROWS if v.in_paper)
PAPER_ROWS: dict[str, str] = {v.name: v.paper_row for v in VARIANT_ROWS}
# The map the paper singles out (its Table 3 and Figure 4), and the one every paired test compares against.
REFERENCE = "marking-deadend"
SWITCHES: tuple[str, ...] = MapSwitches._fields


class VariantError(ValueError):
    """A direction, variant or mode that does not exist, or a combination the rules forbid."""


class UndefinedCombination(VariantError):
    """A (variant, mode) the paper does not define: DFS in the optimal setting."""


def check_choice(name: str, value: object, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise VariantError(f"unknown {name} {value!r}; allowed: {', '.join(allowed)}")


def check(direction: str, variant: str, mode: str) -> Variant:
    """The variant's row, once direction, variant and mode exist and go together."""
    check_choice("direction", direction, DIRECTIONS)
    check_choice("variant", variant, VARIANTS)
    check_choice("mode", mode, MODES)
    row = BY_NAME[variant]
    if row.reachable_only and mode != "reachable":
        raise UndefinedCombination(f"variant {variant!r} is reachable-only: defined only in the reachable setting "
                                   f"(mode=reachable); got mode={mode}")
    return row


def text_direction(direction: str, variant: str) -> str | None:
    """The direction as far as the texts see it: None for a direction-free variant."""
    return None if BY_NAME[variant].direction_free else direction


def variant_for(baseline: str, switches: Mapping[str, object]) -> str:
    """The variant the config's switches describe (``switches``: a value for each of `SWITCHES`).
    ``baseline`` is ``cogmap`` or a baseline's name."""
    values = MapSwitches(**{name: bool(switches[name]) for name in SWITCHES})
    if baseline != "cogmap":
        check_choice("baseline", baseline, ("cogmap", *BASELINES))
        if values.named:
            raise VariantError(f"named=on names the expanded states of a cognitive map; baseline={baseline} has "
                               "none. Allowed: named=off, or a map variant (baseline=cogmap)")
        return baseline
    for name, value in MAP_VARIANTS.items():
        if value == values:
            return name
    raise VariantError(
        f"marking=on needs all_moves=on (got all_moves={values.all_moves}, marking={values.marking}): 'cut' labels "
        "exist only where all four neighbours are listed. Allowed switch settings: "
        + ", ".join(f"{n} (" + ", ".join(f"{k}={v}" for k, v in s._asdict().items() if k != "named") + ")"
                    for n, s in PAPER_MAP_VARIANTS.items()))
