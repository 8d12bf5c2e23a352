"""
The identifier's fits, ROS-free: in the caller's thread or in a separate process.

:func:`fit_window` is one fit of a :class:`rotor_id.nodes.test_points.FitRequest` (its own copy
of the window's data) with the data-length verdict. :class:`FitProcess` runs it in a child
process, so that a fit never waits for the interpreter lock behind the node's subscription
callbacks (Python for every sample at 1 kHz x 3 topics; bench/results/live*.md): the
request goes down a pipe (the window's arrays pickled, a small cost beside a fit), each
Gauss-Newton iteration comes back as it is done (the node publishes it and keeps the iterate as
the next warm start) and the caller can ask, through shared flags, for the fit to stop after its
current iteration (publish what it has) or to be abandoned (a final fit waits).
"""

from dataclasses import dataclass, replace
import multiprocessing
import threading
import time

import numpy as np
from rotor_id.estimation.output_error import STOP
from rotor_id.nodes.live import bound_history, data_length_verdict
from rotor_id.pipeline import identify, model_for

#: the live fits' models, by run-description structure (see :func:`live_model`)
_LIVE_MODELS = {}


class Abandoned(Exception):
    """A fit gave way (a final fit or a service call waits)."""


@dataclass
class FitOptions:
    """How one window is fitted."""

    max_iter: int
    multi_start: bool
    step_tol: float
    targets: tuple            # target σ per unknown (0: none)
    full_verdict: bool = True  # extrapolate how much more data the targets need


def live_model(description):
    """
    ``model_for(description)``, built once per model structure for the live fits.

    A test point fits one run description again and again with only its starting values
    changed (the warm start); building the model was more than half of a final fit's CPU
    (bench/results/final_fit_cpu.md). Keyed on the description without ``initial_guess``,
    i.e. on everything :func:`rotor_id.pipeline.model_for` reads. A fit does not change its
    model; the diagnosis augmentations do, so this cache serves the live fit path only.
    """
    key = repr(replace(description, initial_guess={}))
    model = _LIVE_MODELS.get(key)
    if model is None:
        if len(_LIVE_MODELS) >= 8:       # a node's description changed (a parameter set)
            _LIVE_MODELS.clear()
        model = _LIVE_MODELS[key] = model_for(description)
    return model


def fit_window(request, description, options, progress=None, hurry=None):
    """
    Identify a FitRequest's window; return (Identification, verdict, timing ms).

    ``progress(info)`` is called after every Gauss-Newton iteration; it may return
    :data:`rotor_id.estimation.output_error.STOP` or raise :class:`Abandoned`. ``hurry()``,
    when true after the fit, skips extrapolating how much more data the targets need (the
    verdict then says -1: unknown).
    """
    timing = {}
    started = time.perf_counter()
    cpu0, wait0 = thread_times()
    # no residual-adequacy test here (it was 40 % of a fit's CPU): the identifier checks each
    # final estimate after publishing it (IdentifierNode._check_final), off the latency path
    ident = identify(request.record, description, progress=progress, window_s=request.window_s,
                     max_iter=options.max_iter, multi_start=options.multi_start,
                     step_tol=options.step_tol, check_adequacy=False,
                     model=live_model(description))
    ident.stamp0_ns = request.stamp0_ns
    est = ident.estimate
    timing['identify'] = (time.perf_counter() - started) * 1e3
    timing['gauss_newton'] = est.history[-1]['elapsed'] * 1e3 if est.history else 0.0
    timing['iterations'] = int(est.iterations)
    clock = time.perf_counter()
    std = np.array([est.std_of(n) for n in ident.unknowns])
    verdict = data_length_verdict(std, options.targets)
    if not verdict[0] and options.full_verdict and not (hurry is not None and hurry()):
        # how much more data: from the M⁻¹(t_f) trend
        t, hist = bound_history(ident)
        verdict = data_length_verdict(std, options.targets, t, hist, ident.omega_rad_s)
    timing['verdict'] = (time.perf_counter() - clock) * 1e3
    cpu1, wait1 = thread_times()
    timing['fit_cpu'], timing['fit_cpu_wait'] = (cpu1 - cpu0) * 1e3, (wait1 - wait0) * 1e3
    return ident, verdict, timing


def thread_times(tid=None):
    """
    Return (CPU s, run-queue wait s) of a thread of this process (default: the caller).

    From /proc/<pid>/task/<tid>/schedstat (on CPU, waiting for a CPU): the run-queue wait is the
    time the thread was ready but the machine had no free core. The caller's own CPU time is
    ``time.thread_time()``: schedstat's on-CPU sum is brought up to date only when the thread
    is switched out, so a fit that ran without being preempted read 0.0 ms there. Where the
    file is missing (not Linux) the wait is 0.
    """
    path = ('/proc/thread-self/schedstat' if tid is None
            else f'/proc/self/task/{tid}/schedstat')
    try:
        with open(path) as stat:
            on_cpu, waiting = stat.read().split()[:2]
        on_cpu, waiting = int(on_cpu) / 1e9, int(waiting) / 1e9
    except (OSError, ValueError):
        on_cpu, waiting = float('nan'), 0.0
    return (time.thread_time() if tid is None else on_cpu), waiting


def warm_up():
    """
    Load what a fit needs before the first one: the compiled kernels and the fitting modules.

    Otherwise the first fits of a test point run the numpy path until the kernels' ``auto``
    switch and then load them in the middle of a fit (the first final estimate came 3.9 s after
    its window). Returns the seconds it took.
    """
    started = time.perf_counter()
    from rotor_id.estimation import kernels
    kernels.prefer()
    import rotor_id.adequacy  # noqa: F401 - imported by identify at its first call
    return time.perf_counter() - started


def _serve(conn, stop, abandon):
    """Child process: fit what arrives until told to quit; report iterations as they come."""
    conn.send(('ready', warm_up()))

    def progress(info):
        conn.send(('progress', info))
        if abandon.is_set():
            raise Abandoned
        return STOP if stop.is_set() else None

    while True:
        try:
            message = conn.recv()
        except (EOFError, KeyboardInterrupt):
            return
        if message[0] == 'quit':
            return
        _, request, description, options = message
        try:
            conn.send(('done', fit_window(request, description, options, progress,
                                          hurry=stop.is_set)))
        except Abandoned:
            conn.send(('abandoned', None))
        except KeyboardInterrupt:
            return
        except Exception as exc:            # noqa: B902 - raised again in the node
            try:
                conn.send(('error', exc))
            except Exception:               # noqa: B902 - an exception that does not pickle
                conn.send(('error', RuntimeError(f'{type(exc).__name__}: {exc}')))


class FitProcess:
    """
    :func:`fit_window` in a child process (spawned: a clean interpreter, no forked ROS state).

    One fit at a time, called from the node's worker thread (which blocks on the pipe without
    holding the interpreter lock). ``stop()`` / ``abandon()`` act on the fit in progress.
    """

    def __init__(self):
        context = multiprocessing.get_context('spawn')
        self._stop = context.Event()
        self._abandon = context.Event()
        self._conn, child = context.Pipe()
        self.process = context.Process(target=_serve, args=(child, self._stop, self._abandon),
                                       name='identifier-fit', daemon=True)
        self.process.start()
        child.close()
        self.warm_s = None                # how long the child took to load what fits need
        self._ready_lock = threading.Lock()

    def wait_ready(self):
        """Wait until the child has loaded what a fit needs; return the seconds it took."""
        with self._ready_lock:
            if self.warm_s is None:
                try:
                    kind, payload = self._conn.recv()
                except (EOFError, OSError):
                    kind, payload = 'died', None
                self.warm_s = payload if kind == 'ready' else float('nan')
        return self.warm_s

    def stop(self):
        """Ask the fit in progress to end after its current iteration (it is published)."""
        self._stop.set()

    def abandon(self):
        """Ask the fit in progress to give way after its current iteration (not published)."""
        self._abandon.set()

    def fit(self, request, description, options, progress=None):
        """
        Run :func:`fit_window` in the child; same result, exceptions as in the caller.

        ``progress(info)`` is called here for each iteration (for publishing); its return value
        is ignored: use :meth:`stop` and :meth:`abandon`.
        """
        self._stop.clear()
        self._abandon.clear()
        self.wait_ready()
        self._conn.send(('fit', request, description, options))
        while True:
            kind, payload = self._conn.recv()
            if kind == 'progress':
                if progress is not None:
                    progress(payload)
            elif kind == 'done':
                return payload
            elif kind == 'abandoned':
                raise Abandoned
            else:
                raise payload

    def close(self, timeout=5.0):
        """Stop the child process."""
        try:
            self._conn.send(('quit',))
        except (BrokenPipeError, OSError):
            pass
        self.process.join(timeout)
        if self.process.is_alive():
            self.process.terminate()
            self.process.join(1.0)
