"""What the report's command lines share: naming the store in the jobs' own words.

Jobs take ``tracking.root=DIR`` (and ``tracking.uri=``, ``tracking.experiment=``); `python -m pipeline.report`,
`python -m pipeline.report.study` and `python -m pipeline.inspect` take the same overrides, or ``--tracking-uri``.
"""

from __future__ import annotations

import argparse
import os

from pipeline.workflow.tracking import default_tracking_uri

STORE_KEYS = ("tracking.root", "tracking.uri", "tracking.experiment")


def add_store_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("store", nargs="*", metavar="tracking.KEY=VALUE",
                        help="the store as jobs name it: tracking.root=DIR (default outputs), tracking.uri=URI, "
                             "tracking.experiment=NAME")
    parser.add_argument("--tracking-uri", default=None, help="MLflow tracking URI (default: sqlite under tracking.root)")
    parser.add_argument("--experiment", default=None, help="experiment name (default: cogmap)")


def store_of(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[str, str]:
    """(tracking URI, experiment) from the parsed arguments; a bad override is a usage error naming it.
    Quiets MLflow's per-file download bars, which would print before every answer."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    values: dict[str, str] = {}
    for item in args.store:
        key, sep, value = item.partition("=")
        if not sep or key not in STORE_KEYS or not value:
            parser.error(f"{item!r} is not allowed; expected one of {', '.join(k + '=...' for k in STORE_KEYS)}")
        values[key] = value
    uri = args.tracking_uri or values.get("tracking.uri") or default_tracking_uri(values.get("tracking.root", "outputs"))
    return uri, args.experiment or values.get("tracking.experiment", "cogmap")
