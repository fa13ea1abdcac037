"""Several fits advanced together, their solver runs merged into one batched call per round.

A local fit (scipy.optimize.least_squares in local.fit) asks for one run per trial point and 2p more
where a step is accepted (its Jacobian), one request at a time. On small grids a solver call costs
mostly per call, not per member (the 40 m harness grid: 0.77 s for 1 member, 1.24 s for 7, 3.2 s for 31
on one core), so fits run one after another spend most of their time in per-call overhead. ``Lockstep.map`` runs each fit in its own thread;
a fit's request (``ask``) blocks until every fit still running has asked or finished, then the
calling thread answers all requests with one ``evaluate`` call and the fits go on. The fits' own
arithmetic is small (the GIL is not the bottleneck) and all solver work stays in the calling thread.
"""
from __future__ import annotations

import threading
from typing import Callable, Sequence


class Lockstep:
    """Merge the blocking requests of jobs running in threads into batched calls of ``evaluate``.

    evaluate: list of requests -> list of answers (same order); an exception it raises is raised in
    every job whose request was in that call.
    """

    def __init__(self, evaluate: Callable[[list], list]):
        self._evaluate = evaluate
        self._cv = threading.Condition()
        self._pending: dict[int, object] = {}
        self._answers: dict[int, tuple[bool, object]] = {}
        self._live: set[int] = set()
        self._ids = threading.local()
        self.rounds = 0                    # evaluate calls made

    def ask(self, request):
        """From inside a job of ``map``: the answer to ``request`` (blocks until its round is evaluated)."""
        me = getattr(self._ids, "job", None)
        if me is None:
            return self._evaluate([request])[0]      # not inside map: evaluate at once
        with self._cv:
            self._pending[me] = request
            self._cv.notify_all()
            self._cv.wait_for(lambda: me in self._answers)
            ok, value = self._answers.pop(me)
        if not ok:
            raise value
        return value

    def map(self, fn: Callable, items: Sequence) -> list:
        """[fn(item) for item in items] with the jobs' ``ask`` calls merged per round; a job's exception
        is returned in its place (the caller decides what a failed job means)."""
        items = list(items)
        out: list = [None] * len(items)

        def job(i: int) -> None:
            self._ids.job = i
            try:
                out[i] = fn(items[i])
            except BaseException as e:        # returned to the caller, never lost in a thread
                out[i] = e
            finally:
                with self._cv:
                    self._live.discard(i)
                    self._cv.notify_all()

        with self._cv:
            self._live = set(range(len(items)))
        threads = [threading.Thread(target=job, args=(i,), daemon=True) for i in range(len(items))]
        for t in threads:
            t.start()
        while True:
            with self._cv:
                self._cv.wait_for(lambda: not self._live or set(self._pending) >= self._live)
                if not self._live:
                    break
                batch = sorted(self._pending.items())
                self._pending.clear()
            try:
                answers = [(True, a) for a in self._evaluate([r for _, r in batch])]
            except Exception as e:
                answers = [(False, e)] * len(batch)
            self.rounds += 1
            with self._cv:
                for (i, _), a in zip(batch, answers):
                    self._answers[i] = a
                self._cv.notify_all()
        for t in threads:
            t.join()
        return out
