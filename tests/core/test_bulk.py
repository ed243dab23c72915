import gc

import pytest

from pipeline.core.bulk import bulk_building


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
