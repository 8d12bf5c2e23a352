"""
Worker processes for batches of fits and tests, with the compiled kernels in every one.

Forked once (after :func:`rotor_id.estimation.kernels.prefer` has loaded the kernels) and kept
until closed, so a worker keeps what it prepared from one batch to the next. Jobs are queued
longest known first; batches can run beside each other (threads of this process waiting on the
pool); Ctrl-C stops the caller, which stops the pool.
"""

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
    here, except while a batch runs beside (:meth:`beside`, :meth:`together`).
    """

    def __init__(self, processes):
        self.processes = int(processes)
        self._pool = None
        #: {job key: CPU seconds of its last run}: the longest jobs are queued first
        self.costs = {}
        self._unclaimed = []        # submitted jobs whose result no one has asked for
        self._beside = []           # batches under way in threads of this process (beside)
        #: jobs submitted to queue behind the next batch, not queued yet: [[function, item,
        #: handle or None]] (a lock: batches are queued from threads too)
        self._behind = []
        self._lock = threading.Lock()

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
        alone_here = len(items) <= 1 and not self._beside
        if self.processes <= 1 or not items or alone_here:
            timed = [_timed_call((function, item)) for item in items]
        else:
            order = sorted(range(len(items)), key=lambda i: -self.costs.get(keys[i], math.inf))
            # one job at a time: jobs differ in cost tenfold, and map's default chunks of
            # several leave one worker idle at a batch's end
            queued = self._start().map_async(_timed_call,
                                             [(function, items[i]) for i in order], chunksize=1)
            self._queue_behind()
            done = queued.get()
            timed = [None] * len(items)
            for i, result in zip(order, done):
                timed[i] = result
        for key, (_, cpu_s) in zip(keys, timed):
            if key is not None:
                self.costs[key] = cpu_s
        return [result for result, _ in timed]

    def together(self, calls):
        """
        Return [call()] of independent batches, their jobs queued in the workers at once.

        Each call (a likelihood's batch) waits in a thread of this process while the workers
        run its jobs, a lone job included: the batches overlap, and nothing is computed in
        this process meanwhile (its caches see one thread).
        """
        if self.processes <= 1 or len(calls) <= 1:
            return [call() for call in calls]
        waits = [self.beside(call) for call in calls]
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
        self._beside.append(done)           # (before the thread asks for its first job)
        threading.Thread(target=run, daemon=True).start()

        def result():
            done.wait()
            if done in self._beside:
                self._beside.remove(done)
            if 'error' in out:
                raise out['error']
            return out['value']
        return result

    def submit(self, function, item, behind=False):
        """
        Start ``function(item)`` in a worker beside the batches; return a call that waits for it.

        The job is queued behind those already waiting, and fills a worker that a batch leaves
        idle. ``behind``: queued only once the next batch's jobs are (a result wanted last
        then waits behind that batch instead of holding it up), or when it is asked for if no
        batch comes first. With one process it is computed at that call, if ever. A job never
        waited for is stopped by :meth:`close`.
        """
        if self.processes <= 1:
            return lambda: function(item)
        entry = [function, item, None]
        with self._lock:
            if behind:
                self._behind.append(entry)
            else:
                self._queue(entry)

        def result():
            with self._lock:
                if entry in self._behind:       # no batch came: queued now
                    self._behind.remove(entry)
                    self._queue(entry)
            handle = entry[2]
            if handle in self._unclaimed:
                self._unclaimed.remove(handle)
            return handle.get()
        return result

    def _queue(self, entry):
        """Queue a submitted job [function, item, None] in the pool; its handle fills the None."""
        entry[2] = self._start().apply_async(entry[0], (entry[1],))
        self._unclaimed.append(entry[2])

    def _queue_behind(self):
        """Queue the submitted jobs that wait for a batch (:meth:`submit`), in their order."""
        with self._lock:
            for entry in self._behind:
                self._queue(entry)
            self._behind = []

    def close(self, stop=False):
        """
        End the workers (idempotent); stop them where a job or batch is still under way.

        ``stop``: whatever is under way (a search that failed or was interrupted, whose
        workers may have died with a job: waiting for it would never end).
        """
        if self._pool is not None:
            if stop or any(not handle.ready() for handle in self._unclaimed) \
                    or any(not done.is_set() for done in self._beside):
                self._pool.terminate()
            else:
                self._pool.close()
            self._pool.join()
            self._pool = None
        self._unclaimed, self._beside, self._behind = [], [], []


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
