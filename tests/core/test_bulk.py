import gc
import weakref

import pytest

from pipeline.core.bulk import bulk_building, walked_once


def test_the_collector_is_paused_over_the_block_and_resumes_as_it_was():
    assert gc.isenabled()
    with bulk_building():
        assert not gc.isenabled()
        with bulk_building():  # nested: still paused when the inner block ends
            assert not gc.isenabled()
        assert not gc.isenabled()
    assert gc.isenabled()
    with pytest.raises(RuntimeError):
        with bulk_building():
            raise RuntimeError("a failed build")
    assert gc.isenabled()  # resumed after an error too


def test_a_collector_that_was_off_stays_off():
    gc.disable()
    try:
        with bulk_building():
            assert not gc.isenabled()
        assert not gc.isenabled()
    finally:
        gc.enable()


class _Node:
    def __init__(self):
        self.me = self  # a reference cycle: only the cyclic collector frees it


def test_what_existed_before_the_block_is_left_out_of_its_collections_then_collected_after():
    old = _Node()
    gone = weakref.ref(old)
    with walked_once():
        assert gc.get_freeze_count() > 0
        del old
        young = _Node()
        made = weakref.ref(young)
        del young
        gc.collect()
        assert made() is None  # what the block made is walked and collected
        assert gone() is not None  # what existed before is not walked: its cycle survives the block's collection
    assert gc.get_freeze_count() == 0
    gc.collect()
    assert gone() is None  # handed back: collected as before
    with pytest.raises(RuntimeError):
        with walked_once():
            raise RuntimeError("a failed training")
    assert gc.get_freeze_count() == 0
