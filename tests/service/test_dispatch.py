"""Process-level settings of the service's processes."""

from __future__ import annotations

import gc

from service.dispatch import _GC_THRESHOLDS, tune_gc


def test_tune_gc_freezes_what_is_alive_and_collects_less_often() -> None:
    before = gc.get_threshold()
    try:
        survivor = [[i] for i in range(100)]
        tune_gc()
        assert gc.get_threshold() == _GC_THRESHOLDS
        assert _GC_THRESHOLDS[0] > before[0]
        assert gc.get_freeze_count() >= len(survivor)
        # frozen: in no generation that a collection walks
        walked = {id(o) for g in range(3) for o in gc.get_objects(generation=g)}
        assert id(survivor) not in walked and id(survivor[0]) not in walked
    finally:
        gc.unfreeze()
        gc.set_threshold(*before)
