"""The parallel-for's helper team: every index once, errors reach the caller, concurrent and nested callers; how
torch's idle OpenMP workers wait."""

import threading

import numpy as np
import pytest
import torch

from reconstruction import parallel
from reconstruction.parallel import parallel_for


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def _mark(lo, hi, out):
    out[lo:hi] += 1


def test_every_index_is_run_once(two_threads):
    out = np.zeros(1000, np.int64)
    parallel_for(_mark, 1000, out)
    assert (out == 1).all()


def test_an_error_on_a_helper_reaches_the_caller_and_the_team_recovers(two_threads):
    def fail_on_last_part(lo, hi, n):
        if hi == n:
            raise ValueError("bad part")

    for _ in range(5):  # whichever thread takes the last part, the caller sees the error
        with pytest.raises(ValueError, match="bad part"):
            parallel_for(fail_on_last_part, 100, 100)
    out = np.zeros(100, np.int64)
    parallel_for(_mark, 100, out)
    assert (out == 1).all() and not parallel._team.busy.locked()


def test_concurrent_and_nested_callers_each_cover_their_range(two_threads):
    outs = [np.zeros(4000, np.int64) for _ in range(4)]

    def nested(lo, hi, out):
        # A callable that itself calls parallel_for: the team is busy with its caller, so it runs inline.
        parallel_for(_mark, hi - lo, out[lo:hi])

    threads = [threading.Thread(target=parallel_for, args=(nested, 4000, out)) for out in outs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all((out == 1).all() for out in outs)


def test_a_helper_that_fails_to_start_is_not_waited_for(two_threads, monkeypatch):
    parallel._forget_team()  # a team with no helpers yet
    real_start = threading.Thread.start

    def no_threads_left(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(threading.Thread, "start", no_threads_left)
    with pytest.raises(RuntimeError, match="can't start"):
        parallel_for(_mark, 100, np.zeros(100, np.int64))
    monkeypatch.setattr(threading.Thread, "start", real_start)
    out = np.zeros(100, np.int64)
    caller = threading.Thread(target=parallel_for, args=(_mark, 100, out))
    caller.start()
    caller.join(timeout=30)
    assert not caller.is_alive() and (out == 1).all()


def test_openmp_spins_briefly_unless_the_user_chose_how_it_waits():
    environ = {}
    parallel.configure_openmp(environ)
    assert environ == {"GOMP_SPINCOUNT": str(parallel.OPENMP_SPIN_COUNT)}
    assert parallel.openmp_wait(environ) == f"GOMP_SPINCOUNT={parallel.OPENMP_SPIN_COUNT}"
    for chosen in ({"OMP_WAIT_POLICY": "PASSIVE"}, {"GOMP_SPINCOUNT": "0"}):
        environ = dict(chosen)
        parallel.configure_openmp(environ)
        assert environ == chosen
