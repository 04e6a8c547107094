"""processing.pools.slot_map: the workers share the jobs one at a time, the caller among them."""

import threading

import pytest

from processing.pools import slot_map, thread_map

#: A hang detector, far above what any job here needs (the jobs wait for each other only).
HANG_S = 60.0


def test_a_worker_held_up_holds_up_only_the_job_it_has():
    # job 0 cannot finish before every other job has: with a fixed share per worker (jobs 0-3 on
    # one, 4-7 on the other) its worker never reaches jobs 1-3 and the wait runs out
    n = 8
    others_done = threading.Event()
    lock = threading.Lock()
    done = []

    def job(k):
        if k == 0:
            assert others_done.wait(HANG_S), "job 0 waited for jobs its own worker was to take"
        else:
            with lock:
                done.append(k)
                if len(done) == n - 1:
                    others_done.set()
        return k * k

    assert thread_map(job, [(k,) for k in range(n)], 2) == [k * k for k in range(n)]


def test_slot_0_is_the_calling_thread_and_each_slot_one_thread():
    seen = []
    lock = threading.Lock()
    started = threading.Barrier(2, timeout=HANG_S)

    def job(slot, k):
        if k < 2:
            started.wait()  # the first two jobs run at once: both workers are busy
        with lock:
            seen.append((slot, threading.get_ident()))
        return slot

    slots = slot_map(job, [(k,) for k in range(12)], 2)
    assert sorted(set(slots)) == [0, 1]
    idents = {}
    for slot, ident in seen:
        idents.setdefault(slot, set()).add(ident)
    assert idents[0] == {threading.get_ident()}
    assert len(idents[1]) == 1 and idents[1] != idents[0]


def test_an_error_is_raised_once_no_job_is_running():
    running = []
    lock = threading.Lock()
    release = threading.Event()

    def job(k):
        with lock:
            running.append(k)
        try:
            if k == 1:
                raise ValueError("job 1 failed")
            release.wait(0.05)  # the others are still inside their jobs while job 1 fails
        finally:
            with lock:
                running.remove(k)

    with pytest.raises(ValueError, match="job 1 failed"):
        thread_map(job, [(k,) for k in range(6)], 2)
    assert running == []


def test_one_thread_or_one_job_runs_here_in_order():
    here = threading.get_ident()
    got = slot_map(lambda slot, k: (slot, threading.get_ident(), k), [(k,) for k in range(5)], 1)
    assert got == [(0, here, k) for k in range(5)]
    assert slot_map(lambda slot, k: (slot, threading.get_ident()), [(7,)], 4) == [(0, here)]
