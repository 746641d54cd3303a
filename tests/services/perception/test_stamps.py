"""The stamp rules for one source, on their own (the service's use is in test_odd_input.py)."""

from __future__ import annotations

import math

from robonav.services.perception.stamps import OK, RESTART, STAMP_RESTART_SAMPLES, StampOrder

NOW = 1_800_000_000.0


def test_in_order_stamps_pass_and_the_future_never_becomes_the_reference() -> None:
    order = StampOrder(future_tolerance_s=1.0, jump_back_s=1.0)
    assert order.judge(NOW - 5.0, NOW) == OK
    assert order.judge(NOW + 0.5, NOW) == OK  # within the tolerance of clock skew
    assert order.judge(NOW + 60.0, NOW) == "future_stamp"
    assert order.last == NOW + 0.5
    assert order.judge(NOW + 0.6, NOW + 0.1) == OK
    assert order.judge(math.nan, NOW) == "bad_stamp" and order.judge(math.inf, NOW) == "bad_stamp"


def test_small_steps_back_are_out_of_order_and_repeats_only_where_allowed() -> None:
    frames = StampOrder(1.0, 1.0)
    joints = StampOrder(1.0, 1.0, allow_equal=True)
    for order in (frames, joints):
        assert order.judge(NOW, NOW) == OK
        assert order.judge(NOW - 0.5, NOW) == "out_of_order"
    assert frames.judge(NOW, NOW) == "out_of_order"
    assert joints.judge(NOW, NOW) == OK


def test_a_source_that_jumps_back_is_restarted_after_enough_samples_in_a_row() -> None:
    order = StampOrder(1.0, 1.0)
    assert order.judge(NOW, NOW) == OK
    verdicts = [order.judge(NOW - 100.0 + 0.1 * k, NOW) for k in range(STAMP_RESTART_SAMPLES + 1)]
    assert verdicts == ["jumped_back"] * (STAMP_RESTART_SAMPLES - 1) + [RESTART, OK]
    assert order.last == NOW - 100.0 + 0.1 * STAMP_RESTART_SAMPLES


def test_strays_interleaved_with_a_good_stream_or_out_of_order_among_themselves_never_restart_it() -> None:
    order = StampOrder(1.0, 1.0)
    for k in range(20):
        assert order.judge(NOW + 0.01 * k, NOW + 1.0) == OK
        assert order.judge(5.0 + k, NOW + 1.0) == "jumped_back"
    order = StampOrder(1.0, 1.0)
    assert order.judge(NOW, NOW) == OK
    assert [order.judge(NOW - 100.0 - k, NOW) for k in range(5)] == ["jumped_back"] * 5  # each older than the last
    order.reset()
    assert order.last is None and order.judge(NOW - 100.0, NOW) == OK
