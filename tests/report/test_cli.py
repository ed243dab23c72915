"""The store arguments the report's commands share."""

from __future__ import annotations

import argparse

import pytest

from pipeline.report.cli import add_store_arguments, store_of


def test_the_store_is_named_as_jobs_name_it(tmp_path):
    parser = argparse.ArgumentParser()
    add_store_arguments(parser)
    uri, experiment = store_of(parser, parser.parse_args([f"tracking.root={tmp_path}", "tracking.experiment=x"]))
    assert uri == f"sqlite:///{tmp_path.resolve()}/mlflow.db" and experiment == "x"
    assert store_of(parser, parser.parse_args(["--tracking-uri", "sqlite:///a.db"]))[0] == "sqlite:///a.db"
    with pytest.raises(SystemExit):
        store_of(parser, parser.parse_args(["tracking.rot=/x"]))
