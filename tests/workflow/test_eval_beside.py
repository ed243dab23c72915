"""The eval's validation worlds decoded in a forked copy of the job (`evaluation._decoded_beside`): the copy runs
the work on one torch thread while the block runs here on one, the caller's threads come back after, a failing copy
costs the block nothing (the caller redoes what is missing), and a block that fails ends the copy."""

import json
import os
import time

import pytest
import torch

from pipeline.workflow.evaluation import _decoded_beside


@pytest.fixture
def two_threads():
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(threads)


def _recorder(path, seconds=0.0):
    def work(log=True):
        time.sleep(seconds)
        path.write_text(json.dumps({"pid": os.getpid(), "threads": torch.get_num_threads(), "log": log}))
    return work


def test_the_work_runs_in_a_copy_on_one_thread_while_the_block_runs_on_one(tmp_path, two_threads):
    record = tmp_path / "work.json"
    with _decoded_beside(_recorder(record, 0.5)):
        assert torch.get_num_threads() == 1 and not record.exists()  # the copy is still at work
    assert torch.get_num_threads() == 2
    done = json.loads(record.read_text())  # written before the block ended: the block waits for the copy
    assert done["pid"] != os.getpid() and done["threads"] == 1 and done["log"] is False


def test_a_failing_copy_costs_the_block_nothing(tmp_path, two_threads, capfd):
    def boom(log=True):
        raise RuntimeError("the copy failed")
    with _decoded_beside(boom):
        pass
    assert torch.get_num_threads() == 2 and "the copy failed" in capfd.readouterr().err


def test_a_failing_block_ends_the_copy(tmp_path, two_threads):
    record = tmp_path / "work.json"
    started = time.perf_counter()
    with pytest.raises(ValueError, match="block failed"):
        with _decoded_beside(_recorder(record, 30)):
            raise ValueError("block failed")
    assert time.perf_counter() - started < 10 and not record.exists() and torch.get_num_threads() == 2


def test_nothing_runs_beside_on_one_thread_or_without_work(tmp_path):
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        record = tmp_path / "work.json"
        with _decoded_beside(_recorder(record)):
            pass
        assert not record.exists()
        with _decoded_beside(None):
            assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
