"""The garbage collector's heap frozen while a camera runs (engine/loop/heap.py): what is alive when
the camera starts is out of the collections' walk until the last camera stops."""

import gc

import pytest

from monotracker.engine.loop import heap
from monotracker.engine.loop.heap import HeapFreeze

from .conftest import plan_sample


class _Cycle:
    """An object in a reference cycle: only the cyclic collector can free it."""

    def __init__(self):
        self.me = self


def _walked(obj) -> bool:
    """``obj`` is among the objects a full collection walks (not in the permanent generation)."""
    return any(o is obj for o in gc.get_objects())


def test_holders_share_one_freeze_and_the_last_release_unfreezes():
    before = heap.holders()
    if before:
        pytest.skip("another camera of this process holds the heap")   # its own test covers it
    kept = _Cycle()
    a, b = HeapFreeze(), HeapFreeze()
    a.hold()
    assert gc.get_freeze_count() > 0 and not _walked(kept) and heap.holders() == 1
    made_after = _Cycle()
    assert _walked(made_after)                     # what comes after the freeze is collected as usual
    b.hold()
    a.hold()                                       # idempotent: still one hold for a
    assert heap.holders() == 2
    a.release()
    assert gc.get_freeze_count() > 0 and not _walked(kept)   # b still runs
    b.release()
    b.release()                                    # idempotent
    assert heap.holders() == 0 and gc.get_freeze_count() == 0 and _walked(kept)
    off = HeapFreeze(enabled=False)
    assert off.hold() == 0.0 and not off.held and gc.get_freeze_count() == 0


@pytest.mark.parametrize("freeze", [True, False])
def test_a_running_camera_keeps_the_heap_frozen_until_it_stops(make_session, freeze):
    if heap.holders():
        pytest.skip("another camera of this process holds the heap")
    s = make_session(clock="sim", camera="sim-points", freeze_heap=freeze)
    plan_sample(s)
    kept = _Cycle()
    assert s.start_camera().ok
    s.advance(0.2)
    assert (gc.get_freeze_count() > 0) == freeze and _walked(kept) != freeze
    assert s.stop_camera().ok
    assert gc.get_freeze_count() == 0 and _walked(kept)
    assert s.start_camera().ok
    assert (gc.get_freeze_count() > 0) == freeze
    s.shutdown()                                   # shutting down with the camera running releases it too
    assert gc.get_freeze_count() == 0


def test_freeze_heap_must_be_a_bool():
    from monotracker.engine import SessionConfig
    from monotracker.errors import InputError

    with pytest.raises(InputError, match="freeze_heap must be True or False"):
        SessionConfig(freeze_heap="yes").validate()
