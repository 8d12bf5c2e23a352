"""
Compiled kernels (numba) of the simulator's RK4 recursion, loaded only where they pay.

A Gauss-Newton iteration of the 7-parameter wake case is about 10⁵ multiply-adds; the
vectorised numpy code of :mod:`rotor_id.estimation.simulate` spends 30-70 times that in the
interpreter (bench/ml_vs_peers.py). The kernel here runs one RK4 step after another for the
state and all its sensitivities, with F, g, ∂F/∂p and ∂g/∂p evaluated by the model at the stage
times as before (any :class:`rotor_id.physics.models.LinearModel`, time-invariant or periodic).
∂F/∂p enters as its non-zero entries only, which the kernel finds per call. Time-invariant
records go through :func:`affine_kernels` instead (one map per sample interval, prepared once
per parameter vector; see :class:`rotor_id.estimation.simulate.TimeInvariantPlan`).

It is the same arithmetic as the numpy path: the RK4 stages of the state and of the variational
equations S′ = F S + (∂F/∂p) x + ∂g/∂p evaluated at the state's stages, which is the exact
derivative of the RK4 step map (test/estimation/test_kernels.py checks agreement to 1e-12).

Loading numba costs 0.4-1 s (import, then the cached machine code), more than a whole
``rotor-id identify`` of a short record takes. So with ``ROTOR_ID_KERNELS=auto`` (the default)
the numpy code runs until the simulations and filters it did have taken
:data:`AUTO_SWITCH_SECONDS` of CPU time (not wall time, which a loaded machine inflates); then
the kernel is loaded and used from there on (Monte Carlo studies, diagnosis, long records).
``ROTOR_ID_KERNELS=numba`` loads it at the first simulation, ``numpy`` never does (the
reference). Where numba is missing or fails to compile, the numpy path is used and
:func:`status` says why.

The machine code is cached next to this file (numba ``cache=True``), or, where that directory is
read-only, in numba's per-user cache directory (``NUMBA_CACHE_DIR`` overrides both); with no
writable place numba compiles at every start (about 2 s) and still gives the same results.
"""

import os
import time
from types import ModuleType
from typing import Any, Callable

import numpy as np

MODES = ('auto', 'numba', 'numpy')
#: CPU seconds of numpy simulation after which ``auto`` loads the kernel (about its load cost).
AUTO_SWITCH_SECONDS = 0.5

_state: dict[str, Any] = {'kernel': None, 'tried': False, 'error': None, 'numpy_seconds': 0.0,
                          'load_seconds': None, 'module': None}


def mode() -> str:
    """Return the kernel mode from ``ROTOR_ID_KERNELS`` (auto, numba or numpy)."""
    value = os.environ.get('ROTOR_ID_KERNELS', 'auto').strip().lower() or 'auto'
    if value not in MODES:
        raise ValueError(f'ROTOR_ID_KERNELS={value!r}: use one of {", ".join(MODES)}')
    return value


def status() -> dict[str, Any]:
    """Return a dict: mode, kernel loaded?, why not, its load time, numpy seconds so far."""
    return {'mode': mode(), 'loaded': _state['kernel'] is not None, 'error': _state['error'],
            'load_seconds': _state['load_seconds'], 'numpy_seconds': _state['numpy_seconds']}


def note_numpy_seconds(seconds: float) -> None:
    """Account CPU time spent in the numpy recursions (drives the ``auto`` switch)."""
    _state['numpy_seconds'] += seconds


def rk4_kernel() -> Callable[..., Any] | None:
    """Return the compiled RK4 scan, or None when the numpy path is to be used now."""
    if _state['kernel'] is not None:
        return _state['kernel']
    chosen = mode()
    if chosen == 'numpy' or _state['tried']:
        return None
    if chosen == 'auto' and _state['numpy_seconds'] < AUTO_SWITCH_SECONDS:
        return None
    return load()


#: Inputs of ``filter_scan`` (Phi, c, Q, H, d, y, x0, R, P0): the arguments before ``steady``.
_FILTER_INPUTS = 9


def filter_kernel() -> Callable[..., Any] | None:
    """
    Return the compiled Kalman filter of stacked models, or None (as :func:`rk4_kernel`).

    Its array inputs are passed on C-contiguous, writable and float64, the one type signature
    that :func:`load` compiles or reads from the cache. numba specialises on layout and
    read-only flags, and a view it had not seen (a read-only slice of a single-interval
    batch, a non-contiguous stack) would be compiled at its first call: a stall of seconds
    in the middle of a live run (the state estimator of a 5-bladed rig published nothing for
    4 s while ``filter_scan`` compiled a read-only variant).
    """
    if rk4_kernel() is None:
        return None
    scan = _state['module'].filter_scan

    def canonical_scan(*args):
        inputs = [np.require(a, np.float64, ('C', 'W')) for a in args[:_FILTER_INPUTS]]
        return scan(*inputs, *args[_FILTER_INPUTS:])
    return canonical_scan


def affine_kernels() -> ModuleType | None:
    """Return the module with the time-invariant kernels (interval_map, affine_scan), or None."""
    if rk4_kernel() is None:
        return None
    return _state['module']


def initial_state_kernel() -> Callable[..., Any] | None:
    """Return the compiled ∂ν/∂x(t0) recursion of filter error, or None."""
    if rk4_kernel() is None:
        return None
    return _state['module'].initial_state_innovations


def filter_sensitivity_kernel() -> Callable[..., Any] | None:
    """
    Return the compiled filter with analytic sensitivities (filter error), or None (numpy).

    Loaded with the RK4 kernel (same switch); a failure here leaves the other kernels in use.
    """
    if rk4_kernel() is None:
        return None
    if 'sensitivity' not in _state:
        try:
            from rotor_id.estimation import _filter_kernels_numba
            _filter_kernels_numba.warm_up()
            _state['sensitivity'] = _filter_kernels_numba.sensitivity_scan
        except Exception as err:  # noqa: B902 - numba's compile errors: use numpy
            _state['sensitivity'] = None
            _state['error'] = f'filter sensitivities: {type(err).__name__}: {err}'
    return _state['sensitivity']


def load() -> Callable[..., Any] | None:
    """Import numba and compile (or load from the cache) the kernel; None if that fails."""
    if _state['kernel'] is not None or _state['tried']:
        return _state['kernel']
    _state['tried'] = True
    start = time.perf_counter()
    try:
        from rotor_id.estimation import _kernels_numba
        kernel = _kernels_numba.rk4_scan
        _kernels_numba.warm_up()
        _kernels_numba.warm_up_filter()
        _kernels_numba.warm_up_affine()
        _kernels_numba.warm_up_gn()
    except Exception as err:  # noqa: B902 - ImportError, numba's compile errors: use numpy
        _state['error'] = f'{type(err).__name__}: {err}'
        return None
    _state['load_seconds'] = time.perf_counter() - start
    _state['module'] = _kernels_numba
    _state['kernel'] = kernel
    return kernel


def prefer() -> Callable[..., Any] | None:
    """
    Load the kernel now unless ``ROTOR_ID_KERNELS=numpy``: for callers about to simulate a lot.

    A Monte Carlo study or a diagnosis calls this before it forks its workers, so that they
    inherit the loaded kernel instead of each running numpy until the ``auto`` switch and
    loading it again. Returns the kernel or None.
    """
    if mode() == 'numpy':
        return None
    return load()


def main() -> int:
    """
    Load (compile or read from the cache) the kernel and print how long that took.

    Exits 0 either way (``make build`` calls it): without the kernel everything runs on numpy.
    """
    kernel = prefer()
    if kernel is not None:
        filter_sensitivity_kernel()            # compile it into the cache as well
    state = status()
    if kernel is None:
        print(f'rotor_id kernels: numpy only ({state["error"] or "ROTOR_ID_KERNELS=numpy"})')
        return 0
    print(f'rotor_id kernels: compiled kernel ready in {state["load_seconds"]:.2f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
