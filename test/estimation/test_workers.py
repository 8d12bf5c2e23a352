"""The worker pool: results in order, the longest known jobs first, batches beside."""

import time

import pytest
from rotor_id.estimation.workers import Workers


def _started(seconds):
    """Sleep (no CPU) and return when this job started, on the clock all processes share."""
    start = time.monotonic()
    time.sleep(seconds)
    return start


def _busy(item):
    """Spend CPU for about ``item`` seconds; return the item."""
    end = time.process_time() + item
    while time.process_time() < end:
        pass
    return item


def test_results_come_in_order_and_each_key_keeps_its_cost():
    workers = Workers(2)
    try:
        items = [0.2, 0.0, 0.1]
        assert workers.apply(_busy, items, ['a', 'b', 'c']) == items
    finally:
        workers.close()
    # the CPU seconds each job took, measured where it ran
    assert workers.costs['a'] > workers.costs['c'] > workers.costs['b']
    assert 0.15 < workers.costs['a'] < 0.5


def test_the_longest_known_job_is_queued_before_shorter_ones():
    workers = Workers(2)
    workers.costs.update(short=0.01, long=1.0)
    try:
        # two workers: the first two jobs queued start at once, the third when one ends
        starts = dict(zip(['short', 'long', 'new'],
                          workers.apply(_started, [0.3, 0.3, 0.3], ['short', 'long', 'new'])))
    finally:
        workers.close()
    # a job never run (no cost yet) and the long one first; the short one after them
    assert starts['short'] - max(starts['long'], starts['new']) > 0.2


def test_a_submitted_job_runs_beside_and_one_never_waited_for_is_stopped_at_close():
    workers = Workers(2)
    try:
        result = workers.submit(_started, 0.0)
        assert result() <= time.monotonic()
        workers.submit(_started, 60.0)       # asked for by no one
        closing = time.monotonic()
    finally:
        workers.close()
    # terminated at close, not waited for
    assert time.monotonic() - closing < 30.0


def test_with_one_process_a_submitted_job_is_computed_when_asked_for():
    workers = Workers(1)
    result = workers.submit(_started, 0.0)
    asked = time.monotonic()
    assert result() >= asked
    workers.close()


def _pid(_):
    import os
    return os.getpid()


def test_a_batch_begun_beside_runs_while_this_process_goes_on():
    import os
    workers = Workers(2)
    try:
        begun = time.monotonic()
        wait = workers.beside(lambda: workers.apply(_started, [0.5, 0.5]))
        # meanwhile a lone job goes to a worker too (this process computes nothing)
        assert workers.apply(_pid, [None]) != [os.getpid()]
        started = wait()
        assert max(started) - begun < 0.4        # both began at once, not after a wait
        assert workers.apply(_pid, [None]) == [os.getpid()]   # ended: a lone job here again
    finally:
        workers.close()


def test_with_one_process_a_batch_begun_beside_is_computed_when_asked_for():
    workers = Workers(1)
    wait = workers.beside(lambda: workers.apply(_started, [0.0]))
    asked = time.monotonic()
    assert wait()[0] >= asked
    workers.close()


def test_a_batch_begun_beside_and_never_waited_for_is_stopped_at_close():
    workers = Workers(2)
    workers.beside(lambda: workers.apply(_started, [60.0, 60.0]))    # the search failed
    closing = time.monotonic()
    workers.close()
    assert time.monotonic() - closing < 30.0     # terminated, not waited for


def test_an_error_in_a_batch_begun_beside_is_raised_where_it_is_waited_for():
    workers = Workers(2)
    try:
        wait = workers.beside(lambda: workers.apply(_started, ['not a number']))
        with pytest.raises(TypeError):
            wait()
    finally:
        workers.close()


def test_a_filler_takes_a_worker_a_batch_leaves_idle_and_no_other():
    workers = Workers(2)
    try:
        filler = workers.submit(_started, 0.0, filler=True)
        time.sleep(0.3)
        assert filler.handle is None        # no batch under way: it waits
        # a batch of one long job and one short: the filler takes the short one's worker
        # while the long one still runs
        queued = time.monotonic()
        starts = workers.apply(_started, [1.0, 0.2])
        assert filler() - queued > 0.15 and filler() < starts[0] + 0.9
        # never ahead of a batch's own jobs: with four on two workers, from the tail on
        filler = workers.submit(_started, 0.0, filler=True)
        starts = workers.apply(_started, [0.3] * 4)
        assert filler() - max(starts) > 0.2
        # none idle (no batch under way): it waits, and is queued when asked for
        waiting = workers.submit(_started, 0.0, filler=True)
        time.sleep(0.3)
        assert waiting.handle is None
        asked = time.monotonic()
        assert waiting() >= asked
        # one given up is never queued
        given_up = workers.submit(_started, 0.0, filler=True)
        given_up.cancel()
        workers.apply(_started, [0.3, 0.0])
        assert given_up.handle is None
    finally:
        workers.close()


def test_with_one_process_a_filler_is_computed_only_when_asked_for():
    workers = Workers(1)
    given_up = workers.submit(_busy, 60.0, filler=True)
    given_up.cancel()                       # never computed (the test would take a minute)
    assert workers.submit(_busy, 0.0, filler=True)() == 0.0


def test_batches_run_together_are_queued_in_the_order_of_the_calls():
    workers = Workers(2)

    def first():
        time.sleep(0.3)                     # its preparation: the next batch still waits
        return workers.apply(_started, [0.4, 0.4])
    try:
        (a, b), (c,) = workers.together([first, lambda: workers.apply(_started, [0.0])])
    finally:
        workers.close()
    # the first call's two jobs took both workers; the second's waited for one of them
    assert c - max(a, b) > 0.3
