"""The exchange between the processes of a distributed run (tuning/distributed.py, the tuner's share
in tuning/design/start_share.py), in this process: each 'process' a thread over an in-memory
key-value store (tests/cluster.py), so the order of the calls, the errors that travel in them and
the keys left behind are checked without a runtime. A process that would wait for one that stopped
fails the test after 20 s."""

import numpy as np
import pytest
from cluster import in_threads

from jaxcart import parallel
from jaxcart.errors import UserError
from tuning.design.start_share import StartShare


def test_rows_reach_every_process_and_no_key_is_left(monkeypatch):
    def work(ex):
        first = ex.allgather({"x": np.arange(3) * ex.index})
        second = ex.allgather({"y": np.float64(ex.index)})
        return first, second, ex.finish()

    out = in_threads(monkeypatch, work, count=3)
    for first, second, _ in out:
        for p in range(3):
            np.testing.assert_array_equal(first[p]["x"], np.arange(3) * p)
            assert second[p]["y"] == p
    assert [done for *_, done in out] == [True, False, False]  # process 0 reports
    assert parallel.publish.__self__.data == {}  # every payload deleted once fetched


def test_an_error_on_one_process_is_raised_on_every_one(monkeypatch):
    # Process 1 fails between two exchanges: it sends its error in its next call, where
    # process 0 waits for its rows, and both raise the same one line at once.
    def work(ex):
        with ex.carry():
            ex.allgather({"x": np.ones(2)})
            if ex.index == 1:
                raise RuntimeError("boom\nsecond line of a long message")
            ex.allgather({"x": np.ones(2)})
            ex.finish()

    out = in_threads(monkeypatch, work)
    # Not after the store's wait: that would end in its TimeoutError, not in the one line.
    for exc in out:
        assert type(exc) is UserError
        assert str(exc) == "RuntimeError in process 1 of 2: boom"
    assert isinstance(out[1].__cause__, RuntimeError)  # the failing process keeps its trace


def test_a_user_error_travels_as_it_is(monkeypatch):
    # Process 0 cannot read an input before any exchange; process 1 waits at the first one.
    def work(ex):
        with ex.carry():
            if ex.index == 0:
                raise UserError("run.toml: no such file")
            ex.sync()

    assert [str(e) for e in in_threads(monkeypatch, work)] == ["run.toml: no such file"] * 2


def test_the_error_of_least_rank_then_least_process_wins(monkeypatch):
    def failing(ranks):
        def work(ex):
            ex.allgather(
                {}, failure=UserError(f"error of process {ex.index}"), rank=ranks[ex.index]
            )

        return {str(e) for e in in_threads(monkeypatch, work, count=len(ranks))}

    assert failing([2, 1, 5]) == {"error of process 1"}
    assert failing([1, 0, 0]) == {"error of process 1"}  # a tie: the least process index


def test_an_error_after_the_last_exchange_is_raised_in_finish(monkeypatch):
    def work(ex):
        with ex.carry():
            ex.allgather({"x": np.zeros(1)})
            if ex.index == 1:
                raise KeyError("late")
            return ex.finish()

    assert [str(e) for e in in_threads(monkeypatch, work)] == [
        "KeyError in process 1 of 2: 'late'"
    ] * 2


def test_errors_of_the_exchange_or_after_it_are_not_sent_again(monkeypatch):
    # Nested blocks: the error the inner one sent goes up the outer one as it is, so both
    # processes made the same one call. After finish, process 0 (which reports alone) raises
    # its own error while process 1 has returned: nobody is left to send it to.
    def nested(ex):
        try:
            with ex.carry(), ex.carry():
                if ex.index == 1:
                    raise ValueError("bad")
                ex.sync()
        except UserError as exc:
            return str(exc), ex.calls

    assert in_threads(monkeypatch, nested) == [("ValueError in process 1 of 2: bad", 1)] * 2

    def after(ex):
        with ex.carry():
            if ex.finish():
                raise OSError("disk full")
            return "done"

    out = in_threads(monkeypatch, after)
    assert type(out[0]) is OSError and out[1] == "done"


def test_start_share_with_too_few_starts_fails_on_every_process():
    # Checked alike on every process (not only where a share is empty): none waits.
    for i in range(3):
        with pytest.raises(UserError, match="at least one start each; give --starts 3"):
            StartShare(2, i, 3)
