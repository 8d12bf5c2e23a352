"""
Worker processes for batches of fits and tests, with the compiled kernels in every one.

Forked once (after :func:`rotor_id.estimation.kernels.prefer` has loaded the kernels) and kept
until closed, so a worker keeps what it prepared from one batch to the next. Jobs are queued
longest known first; batches can run beside each other (threads of this process waiting on the
pool); a job submitted as a filler takes a worker that a batch leaves idle before its end;
Ctrl-C stops the caller, which stops the pool.
"""

from functools import partial
import math
import multiprocessing
import signal
import threading
import time

from rotor_id.estimation import kernels


class Workers:
    """
    Worker processes for the candidate fits and score tests, forked once per diagnosis.

    Forked on first use, after the compiled kernels are loaded (:func:`kernels.prefer`), so
    every worker inherits them, and kept until :meth:`close`: a worker holds the record's
    prepared plans from one batch to the next. With one process (or one job) the work runs
    here, except while a batch runs beside (:meth:`beside`, :meth:`together`) or a filler
    waits for the worker it would leave idle (:meth:`submit`).
    """

    def __init__(self, processes):
        self.processes = int(processes)
        self._pool = None
        #: {job key: CPU seconds of its last run}: the longest jobs are queued first
        self.costs = {}
        self._unclaimed = []        # submitted jobs whose result no one has asked for
        self._beside = []           # batches under way in threads of this process (beside)
        #: submitted fillers of idle workers not queued yet (:class:`Submitted`; a lock: jobs
        #: end in the pool's result thread, and batches are queued from threads too)
        self._fillers = []
        self._lock = threading.RLock()
        #: batches queued so far, told to :meth:`together` as each is (on the same lock)
        self._batches = 0
        self._queued = threading.Condition(self._lock)
        #: jobs in the pool (queued or running), and those of them from batches (:meth:`apply`)
        self._in_pool, self._batch_jobs = 0, 0

    def _start(self):
        if self._pool is None:
            kernels.prefer()
            self._pool = multiprocessing.get_context('fork').Pool(
                processes=self.processes, initializer=_leave_interrupts)
        return self._pool

    def apply(self, function, items, keys=None):
        """
        Return [function(item)] in order, in the workers where that pays.

        ``keys`` name the jobs (a tested effect's variant, a fit's new effect): jobs of the
        same key cost alike from one model to the next, so the longest known ones are queued
        first and those never run before them (longest processing time first: a batch ends
        with its short jobs spread over the workers, not one long job alone).
        """
        items = list(items)
        keys = list(keys) if keys is not None else [None] * len(items)
        alone_here = len(items) <= 1 and not self._beside and not self._fillers
        if self.processes <= 1 or not items or alone_here:
            timed = [_timed_call((function, item)) for item in items]
        else:
            order = sorted(range(len(items)), key=lambda i: -self.costs.get(keys[i], math.inf))
            self._start()
            # one job at a time: jobs differ in cost tenfold, and chunks of several leave one
            # worker idle at a batch's end
            with self._lock:
                handles = [self._put(_timed_call, (function, items[i]), batch=True)
                           for i in order]
                self._fill_idle()
                self._batches += 1
                self._queued.notify_all()
            timed = [None] * len(items)
            for i, handle in zip(order, handles):
                timed[i] = handle.get()
        for key, (_, cpu_s) in zip(keys, timed):
            if key is not None:
                self.costs[key] = cpu_s
        return [result for result, _ in timed]

    def together(self, calls):
        """
        Return [call()] of independent batches, their jobs queued in the workers at once.

        Each call (a likelihood's batch) waits in a thread of this process while the workers
        run its jobs, a lone job included: the batches overlap, and nothing is computed in
        this process meanwhile (its caches see one thread). A batch's jobs are queued before
        the next call begins, so they are queued in the order of the calls (the caller puts
        the longest first).
        """
        if self.processes <= 1 or len(calls) <= 1:
            return [call() for call in calls]
        waits = []
        for call in calls:
            with self._queued:
                before = self._batches
                waits.append(self.beside(call))
                self._queued.wait_for(lambda: self._batches != before or waits[-1].done.is_set())
        return [wait() for wait in waits]

    def beside(self, call):
        """
        Start ``call()`` (a batch) in a thread beside what this process does next.

        Return a call that waits for its result. Until then every job, a lone one included,
        is queued in the workers (this process's caches see one thread). With one process,
        ``call`` is made when its result is asked for. A batch no one waited for is stopped
        by :meth:`close` (its thread is a daemon: it never holds up the exit).
        """
        if self.processes <= 1:
            return call
        self._start()
        done, out = threading.Event(), {}

        def run():
            try:
                out['value'] = call()
            except BaseException as exc:  # noqa: B902 - raised again where it is waited for
                out['error'] = exc
            finally:
                done.set()
                with self._queued:
                    self._queued.notify_all()
        self._beside.append(done)           # (before the thread asks for its first job)
        threading.Thread(target=run, daemon=True).start()

        def result():
            done.wait()
            if done in self._beside:
                self._beside.remove(done)
            if 'error' in out:
                raise out['error']
            return out['value']
        result.done = done
        return result

    def submit(self, function, item, filler=False):
        """
        Start ``function(item)`` in a worker beside the batches: a :class:`Submitted` job.

        Calling it waits for the result. The job is queued behind those already waiting.
        ``filler``: work that may not be wanted, queued only where a worker is idle while a
        batch is under way (it costs the batches no time), in the order submitted; else when
        released or asked for. With one process the job is computed when asked for, if ever.
        A job never waited for is stopped by :meth:`close`.
        """
        job = Submitted(self, function, item)
        if self.processes > 1:
            with self._lock:
                if filler:
                    self._fillers.append(job)       # (filled from the next batch on)
                else:
                    self._queue(job)
        return job

    def _put(self, function, argument, batch=False):
        """Queue ``function(argument)`` in the pool (holding the lock); return its handle."""
        self._in_pool += 1
        self._batch_jobs += batch
        ended = partial(self._ended, batch)
        return self._start().apply_async(function, (argument,), callback=ended,
                                         error_callback=ended)

    def _ended(self, batch, _result):
        """Count a job out of the pool (in the pool's result thread); fill an idle worker."""
        with self._lock:
            self._in_pool -= 1
            self._batch_jobs -= batch
            self._fill_idle()

    def _fill_idle(self):
        """Queue fillers while a batch is under way and a worker has nothing queued for it."""
        while self._fillers and self._batch_jobs > 0 and self._in_pool < self.processes \
                and self._pool is not None:
            self._queue(self._fillers.pop(0))

    def _queue(self, job):
        """Queue a submitted job in the pool (holding the lock)."""
        job.handle = self._put(job.function, job.item)
        self._unclaimed.append(job.handle)

    def _release(self, job):
        """Queue a submitted filler now if it still waits for an idle worker."""
        with self._lock:
            if job in self._fillers:
                self._fillers.remove(job)
                self._queue(job)

    def close(self, stop=False):
        """
        End the workers (idempotent); stop them where a job or batch is still under way.

        ``stop``: whatever is under way (a search that failed or was interrupted, whose
        workers may have died with a job: waiting for it would never end).
        """
        with self._lock:
            self._fillers = []              # (a job ending now queues none in a closing pool)
        if self._pool is not None:
            if stop or any(not handle.ready() for handle in self._unclaimed) \
                    or any(not done.is_set() for done in self._beside):
                self._pool.terminate()
            else:
                self._pool.close()
            self._pool.join()
            self._pool = None
        self._unclaimed, self._beside, self._fillers = [], [], []
        self._in_pool, self._batch_jobs = 0, 0


class Submitted:
    """A job submitted to the workers (:meth:`Workers.submit`): call it for its result."""

    def __init__(self, workers, function, item):
        self.workers, self.function, self.item = workers, function, item
        self.handle = None

    def __call__(self):
        """Return the job's result: queue it if it still waits, and wait for it."""
        workers = self.workers
        if workers.processes <= 1:
            return self.function(self.item)
        workers._release(self)
        if self.handle in workers._unclaimed:
            workers._unclaimed.remove(self.handle)
        return self.handle.get()

    def release(self):
        """Queue the job now if it still waits for an idle worker."""
        if self.workers.processes > 1:
            self.workers._release(self)

    def cancel(self):
        """Give the job up: never queued if it still waits; if queued, its result is unread."""
        workers = self.workers
        with workers._lock:
            if self in workers._fillers:
                workers._fillers.remove(self)


def _leave_interrupts():
    """
    Make a worker ignore Ctrl-C: the diagnosis that forked it is interrupted and stops it.

    Interrupted itself, a worker could die inside the pool's task queue and leave it locked:
    the diagnosis then waited forever to stop the pool.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _timed_call(function_and_item):
    """Return (function(item), its CPU seconds): a job as the workers run it."""
    function, item = function_and_item
    start = time.process_time()
    result = function(item)
    return result, time.process_time() - start
