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

``make build`` compiles the kernels ahead of time (numba.pycc, :func:`build_ahead_of_time`)
into an extension module beside this file, named after a hash of the kernels' sources and the
numba, numpy and Python versions: it loads without importing numba, where the just-in-time
kernels cost numba's start-up in every process (bench/results/diagnose_speed.md). Its functions
check every argument's type, layout and writability against the signature it was compiled for,
and pass a call that does not match to the just-in-time kernel (compiled code would read such an
array wrongly; numba compiles that one then). Without that module (no C compiler, other sources)
the just-in-time kernels load instead; ``make build`` compiles them into the cache only then.

The just-in-time machine code is cached next to this file (numba ``cache=True``), or, where that
directory is read-only, in numba's per-user cache directory (``NUMBA_CACHE_DIR`` overrides both);
with no writable place numba compiles at every start (about 2 s) and still gives the same
results.
"""

import hashlib
import importlib
import importlib.util
import json
import multiprocessing
import os
from pathlib import Path
import sys
import time
from types import ModuleType, SimpleNamespace
from typing import Any, Callable

import numpy as np

MODES = ('auto', 'numba', 'numpy')
#: CPU seconds of numpy simulation after which ``auto`` loads the kernel (about its load cost).
AUTO_SWITCH_SECONDS = 0.5

_state: dict[str, Any] = {'kernel': None, 'tried': False, 'error': None, 'numpy_seconds': 0.0,
                          'load_seconds': None, 'module': None, 'compiled': None,
                          'ahead_error': None, 'just_in_time_calls': 0}
_HERE = Path(__file__).resolve().parent
#: the files whose content the ahead-of-time module is built from (its name hashes them)
_KERNEL_SOURCES = ('_kernels_numba.py', '_filter_kernels_numba.py', '_kernels_build.py')
#: which Python scalars a compiled scalar argument takes (anything else: the just-in-time path)
_SCALAR_KINDS = {'float64': (float,), 'int64': (int, np.integer), 'bool': (bool, np.bool_)}


def mode() -> str:
    """Return the kernel mode from ``ROTOR_ID_KERNELS`` (auto, numba or numpy)."""
    value = os.environ.get('ROTOR_ID_KERNELS', 'auto').strip().lower() or 'auto'
    if value not in MODES:
        raise ValueError(f'ROTOR_ID_KERNELS={value!r}: use one of {", ".join(MODES)}')
    return value


def status() -> dict[str, Any]:
    """Return a dict: mode, kernel loaded?, why not, its load time, numpy seconds so far."""
    return {'mode': mode(), 'loaded': _state['kernel'] is not None, 'error': _state['error'],
            'load_seconds': _state['load_seconds'], 'numpy_seconds': _state['numpy_seconds'],
            'compiled': _state['compiled'], 'ahead_error': _state['ahead_error'],
            'just_in_time_calls': _state['just_in_time_calls']}


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

    def canonical_scan(*args, states=None):
        # ``states``: (x_pred, P_pred, x_filt, P_filt) to fill; none kept when not given
        inputs = [np.require(a, np.float64, ('C', 'W')) for a in args[:_FILTER_INPUTS]]
        if states is None:
            K_, n = np.shape(args[6])
            states = (np.empty((K_, 0, n)), np.empty((K_, 0, n, n))) * 2
        return scan(*inputs, *args[_FILTER_INPUTS:], *states)
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
    if 'sensitivity' not in _state and hasattr(_state['module'], 'sensitivity_scan'):
        _state['sensitivity'] = _state['module'].sensitivity_scan
    if 'sensitivity' not in _state:
        try:
            from rotor_id.estimation import _filter_kernels_numba
            _filter_kernels_numba.warm_up()
            _state['sensitivity'] = _filter_kernels_numba.sensitivity_scan
        except Exception as err:  # noqa: B902 - numba's compile errors: use numpy
            _state['sensitivity'] = None
            _state['error'] = f'filter sensitivities: {type(err).__name__}: {err}'
    return _state['sensitivity']


def ahead_of_time_name() -> str:
    """Return the ahead-of-time module's name for these kernel sources and library versions."""
    digest = hashlib.sha256()
    for name in _KERNEL_SOURCES:
        digest.update((_HERE / name).read_bytes())
    digest.update(f'{_numba_version()} {np.__version__} {sys.version}'.encode())
    return f'_kernels_aot_{digest.hexdigest()[:16]}'


def _numba_version() -> str:
    """
    Return numba's version without importing it: from its dist-info directory beside it.

    Every start that loads the kernels asks (:func:`ahead_of_time_name`); importlib.metadata
    took 45 ms of a 0.5 s start, its import and a scan of every installed package, where
    the directory's name takes 2 ms. importlib.metadata where that directory is not found.
    """
    spec = importlib.util.find_spec('numba')
    if spec is not None and spec.origin:
        found = list(Path(spec.origin).parent.parent.glob('numba-*.dist-info'))
        if len(found) == 1:
            return found[0].name[len('numba-'):-len('.dist-info')]
    from importlib.metadata import version
    return version('numba')


def _just_in_time(function: str) -> Callable[..., Any]:
    """Return a kernel's just-in-time dispatcher (numba compiles a signature it has not seen)."""
    _state['just_in_time_calls'] += 1
    if function == 'sensitivity_scan':
        from rotor_id.estimation import _filter_kernels_numba
        return _filter_kernels_numba.sensitivity_scan
    from rotor_id.estimation import _kernels_numba
    return getattr(_kernels_numba, function)


def _checked(function: str, compiled: Callable[..., Any],
             arguments: list[list[Any]]) -> Callable[..., Any]:
    """Wrap a kernel compiled ahead of time: a call off its signature goes just in time."""
    arrays = tuple((i, np.dtype(dtype), ndim, contiguous)
                   for i, (dtype, ndim, contiguous) in enumerate(arguments) if ndim)
    scalars = tuple((i, _SCALAR_KINDS[dtype])
                    for i, (dtype, ndim, _) in enumerate(arguments) if not ndim)
    count = len(arguments)

    def call(*args: Any) -> Any:
        matches = len(args) == count and all(
            type(args[i]) is np.ndarray and args[i].dtype == dtype and args[i].ndim == ndim
            and args[i].flags.writeable and args[i].flags.aligned
            and (args[i].flags.c_contiguous or not contiguous)
            for i, dtype, ndim, contiguous in arrays) and all(
            isinstance(args[i], kinds) and (bool in kinds or not isinstance(args[i], bool))
            for i, kinds in scalars)
        return (compiled if matches else _just_in_time(function))(*args)
    call.__name__ = call.__qualname__ = function
    return call


#: scipy's modules of BLAS and LAPACK function pointers, through which numba's compiled linear
#: algebra (np.dot, np.linalg.solve in a kernel) calls the libraries
_CAPSULE_MODULES = ('cython_blas', 'cython_lapack')


def _load_capsule_modules() -> None:
    """
    Load scipy's BLAS and LAPACK pointer modules without the scipy.linalg package around them.

    numba's compiled code imports them by their full names at its first matrix product, and
    that import runs the package's ``__init__`` first: a third of a second, longer than a small
    diagnosis's whole search. An import by full name is answered by ``sys.modules`` without
    its package, so they are loaded from their files under those names here. Where scipy is
    laid out otherwise, nothing is loaded and numba imports them itself, as it always could.
    """
    try:
        import scipy
        folder = Path(scipy.__file__).parent / 'linalg'
        for name in _CAPSULE_MODULES:
            full = f'scipy.linalg.{name}'
            found = sorted(folder.glob(f'{name}.*.so')) or sorted(folder.glob(f'{name}.*.pyd'))
            if full in sys.modules or not found:
                continue
            spec = importlib.util.spec_from_file_location(full, found[0])
            if spec is None or spec.loader is None:
                continue
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            sys.modules[full] = module
    except Exception:  # noqa: B902 - anything unexpected: numba's own import, as before
        return


def _load_ahead_of_time() -> SimpleNamespace | None:
    """Return the kernels compiled ahead of time (checked), or None (and why, in the status)."""
    name = ahead_of_time_name()
    described = _HERE / f'{name}.json'
    if not described.exists():
        _state['ahead_error'] = f'{name} not built (make build compiles it)'
        return None
    _load_capsule_modules()
    kernels = {}
    for function, built in json.loads(described.read_text()).items():
        module = importlib.import_module(f'rotor_id.estimation.{built["module"]}')
        kernels[function] = _checked(function, getattr(module, function), built['arguments'])
    return SimpleNamespace(**kernels)


def _load_just_in_time() -> ModuleType:
    """Import numba's kernels and compile them (or load them from numba's cache)."""
    from rotor_id.estimation import _kernels_numba
    _kernels_numba.warm_up()
    _kernels_numba.warm_up_filter()
    _kernels_numba.warm_up_affine()
    _kernels_numba.warm_up_gn()
    return _kernels_numba


def load() -> Callable[..., Any] | None:
    """Load the kernels (ahead of time, else numba's just in time); None if neither loads."""
    if _state['kernel'] is not None or _state['tried']:
        return _state['kernel']
    _state['tried'] = True
    start = time.perf_counter()
    module: Any = None
    try:
        module = _load_ahead_of_time()
    except Exception as err:  # noqa: B902 - a module that does not load: just in time
        _state['ahead_error'] = f'{type(err).__name__}: {err}'
    _state['compiled'] = 'ahead of time' if module is not None else 'just in time'
    if module is None:
        try:
            module = _load_just_in_time()
        except Exception as err:  # noqa: B902 - ImportError, numba's compile errors: use numpy
            _state['error'] = f'{type(err).__name__}: {err}'
            _state['compiled'] = None
            return None
    _state['load_seconds'] = time.perf_counter() - start
    _state['module'] = module
    _state['kernel'] = module.rk4_scan
    return _state['kernel']


def build_ahead_of_time() -> str:
    """Compile the kernels ahead of time unless this version is built; return what was done."""
    name = ahead_of_time_name()
    if (_HERE / f'{name}.json').exists():
        return f'{name} up to date'
    from rotor_id.estimation import _kernels_build
    start = time.perf_counter()
    for old in _HERE.glob('_kernels_aot_*'):     # builds of other sources or versions
        old.unlink(missing_ok=True)
    _kernels_build.build(_HERE, name)
    return f'{name} built in {time.perf_counter() - start:.0f} s'


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


#: The just-in-time kernels' warm-ups in two groups, compiled side by side by :func:`main`: the
#: Gauss-Newton kernels with the affine one they call (compiled once, not in both), the others
#: in the second (on a slow 2-core machine 58 s for both, 84 s one after the other).
WARM_UP_GROUPS = ((('_kernels_numba', 'warm_up_affine'), ('_kernels_numba', 'warm_up_gn')),
                  (('_kernels_numba', 'warm_up'), ('_kernels_numba', 'warm_up_filter'),
                   ('_filter_kernels_numba', 'warm_up')))


def _warm_up_group(group: int) -> None:
    """Compile one group of :data:`WARM_UP_GROUPS` into numba's cache (a worker process)."""
    for module, function in WARM_UP_GROUPS[group]:
        getattr(importlib.import_module(f'rotor_id.estimation.{module}'), function)()


def main() -> int:
    """
    Compile the kernels for ``make build``: ahead of time, else just in time; say what it took.

    The module compiled ahead of time is what every process loads; the just-in-time kernels
    serve only where it cannot be built or loaded (no C compiler, edited kernels not yet
    rebuilt) and a call off its signature (compiled then, into numba's cache). So they are
    compiled here only where that module fails: about 2 min of CPU that a machine with a C
    compiler never needs. Exits 0 either way: without either, everything runs on numpy.
    """
    if mode() == 'numpy':
        print('rotor_id kernels: numpy only (ROTOR_ID_KERNELS=numpy)')
        return 0
    try:
        done = build_ahead_of_time()
        if _load_ahead_of_time() is not None:
            print(f'rotor_id kernels: ahead of time: {done}')
            return 0
        why = _state['ahead_error']
    except Exception as err:  # noqa: B902 - no compiler etc.: the just-in-time kernels serve
        why = f'{type(err).__name__}: {err}'
    print(f'rotor_id kernels: not compiled ahead of time ({why}); compiling them just in time')
    start = time.perf_counter()
    try:
        # compiled into the cache by two processes (numba compiles on one core), then loaded
        with multiprocessing.get_context('fork').Pool(len(WARM_UP_GROUPS)) as pool:
            pool.map(_warm_up_group, range(len(WARM_UP_GROUPS)))
        _load_just_in_time()
        from rotor_id.estimation import _filter_kernels_numba
        _filter_kernels_numba.warm_up()
    except Exception as err:  # noqa: B902 - ImportError, numba's compile errors: use numpy
        print(f'rotor_id kernels: numpy only ({type(err).__name__}: {err})')
        return 0
    print(f'rotor_id kernels: just-in-time kernels ready in {time.perf_counter() - start:.2f} s')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
