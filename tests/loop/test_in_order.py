"""Functions on threads beside the caller's, in the order handed over (``ti_fusion/loop/in_order.py``): the order
kept, failures raised where they belong, cancelled and dropped functions neither run nor keep their results, and
a settle cut by Ctrl-C leaving the rest for the next."""

import threading
import time

import pytest

from ti_fusion.loop.in_order import InOrder, Job

WAIT_S = 60  # a bound for a broken queue, not a timing any test depends on


def test_functions_run_in_the_order_handed_over_each_on_a_thread():
    queue, order, threads, names = InOrder("in-order-test"), [], set(), set()

    def step(k, pause):
        time.sleep(pause)  # a later function that would finish first if it did not wait
        order.append(k)
        threads.add(threading.get_ident())
        names.add(threading.current_thread().name)
        return k

    gate = threading.Event()  # the last runs only once let: what take saw is then not raced by it
    jobs = [queue.submit(lambda k=k: step(k, 0.02 * (3 - k))) for k in range(3)]
    jobs.append(queue.submit(lambda: gate.wait() and step(3, 0.0)))
    assert queue.take(jobs[2]) == 2 and order == [0, 1, 2]
    gate.set()
    queue.settle()
    assert order == [0, 1, 2, 3] and threading.get_ident() not in threads and names == {"in-order-test"}


def test_a_failure_is_raised_by_settle_unless_quiet():
    queue = InOrder("in-order-test")
    quiet = queue.submit(lambda: 1 / 0, quiet=True)
    after = queue.submit(lambda: "ran")  # a failure before it does not stop it
    assert queue.take(quiet) is None  # the taker does the work itself
    queue.settle()
    assert after.result == "ran"
    queue.submit(lambda: [][1])
    with pytest.raises(IndexError):
        queue.settle()
    queue.settle()  # raised once


def test_a_cancelled_function_does_not_run():
    queue, gate, ran = InOrder("in-order-test"), threading.Event(), []
    queue.submit(gate.wait)
    job = queue.submit(lambda: ran.append(1), quiet=True)
    job.cancelled = True
    gate.set()
    assert queue.take(job) is None
    queue.settle()
    assert ran == []


def test_a_settle_cut_by_ctrl_c_leaves_the_rest_for_the_next(monkeypatch):
    """A Ctrl-C that arrives while the loop's thread waits (a notebook's interrupted cell, then more frames or
    ``save_map``): the functions not yet waited for are still waited for, and their failures raised, by the
    next ``settle``, so nothing reads the database while an addition still runs on it."""
    queue, gate = InOrder("in-order-test"), threading.Event()
    first = queue.submit(gate.wait)
    queue.submit(lambda: [][1])
    wait, cut, me = Job.wait, [], threading.get_ident()

    def interrupted(job):  # a Ctrl-C reaches the waiting caller only, not a job's thread waiting for the one before
        if not cut and threading.get_ident() == me:
            cut.append(job)
            raise KeyboardInterrupt
        wait(job)

    monkeypatch.setattr(Job, "wait", interrupted)
    with pytest.raises(KeyboardInterrupt):
        queue.settle()
    assert cut == [first]
    gate.set()
    with pytest.raises(IndexError):  # waited for, not forgotten
        queue.settle()
    assert not first._thread.is_alive()


def test_a_dropped_function_keeps_nothing_and_leaves_the_queue():
    """Looks ahead that go unused (a frame the tracked pose did not make a keyframe; every frame of a lost
    stretch): neither their inputs nor their results stay in the queue until the next keyframe settles it."""
    queue, gate, started = InOrder("in-order-test"), threading.Event(), threading.Event()
    done = queue.submit(lambda: "ahead", quiet=True)
    done.wait()
    queue.drop(done)
    assert done.result is None and done not in queue._jobs
    running = queue.submit(lambda: started.set() or gate.wait() and "ahead", quiet=True)
    waiting = queue.submit(lambda: "never", quiet=True)
    assert started.wait(WAIT_S), "the function after a dropped one did not start"
    queue.drop(running)  # dropped while it runs: it stays until done, then keeps no result
    queue.drop(waiting)  # not started: it does not run
    assert running in queue._jobs and waiting in queue._jobs
    gate.set()
    queue.settle()
    assert running.result is None and waiting.result is None and waiting._fn is None and queue._jobs == []
