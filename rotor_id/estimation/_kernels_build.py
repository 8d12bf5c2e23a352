"""
Compile the numba kernels ahead of time (numba.pycc) into an extension module next to them.

Imported only from :func:`rotor_id.estimation.kernels.build_ahead_of_time` (``make build``).
Every exported kernel is compiled for one signature: the numba types of the example arguments
that its warm-up passes (``<kernel>_example`` beside it, typed without compiling anything just
in time) and the return type declared here. The kernels are compiled in :data:`PARTS`, one
process and one extension module ``_kernels_aot_<key>_<part>`` each, side by side on two
cores; then ``_kernels_aot_<key>.json`` names each kernel's module and its argument types. The
key hashes the kernels' sources and the numba, numpy and Python versions, so a module built
from other sources is never found. The Python wrappers release the GIL as the ``nogil``
kernels do.
"""

import json
import multiprocessing
import os
from pathlib import Path
import tempfile
import warnings

from rotor_id.estimation import _filter_kernels_numba, _kernels_numba

#: the kernels :mod:`rotor_id.estimation.kernels` calls: the module that defines them and what
#: they return (a wrong one fails the build: the just-in-time kernels then serve)
EXPORTS = {'rk4_scan': (_kernels_numba, 'none'), 'filter_scan': (_kernels_numba, 'none'),
           'initial_state_innovations': (_kernels_numba, 'none'),
           'affine_run': (_kernels_numba, 'none'), 'gn_iteration': (_kernels_numba, 'int64'),
           'gn_fit': (_kernels_numba, 'int64'), 'clock_ns': (_kernels_numba, 'int64'),
           'sensitivity_scan': (_filter_kernels_numba, 'float64')}


#: the kernels in two groups compiled side by side: the affine and Gauss-Newton kernels, which
#: share their inner functions, and the general RK4 scan with the filters. On a slow 2-core
#: machine 84 s (116 s of CPU), where one process takes 106 s; splitting the Gauss-Newton
#: kernels further compiles their shared inner functions twice (3 parts: 100 s, 178 s of CPU)
PARTS = (('affine_run', 'gn_iteration', 'gn_fit', 'clock_ns'),
         ('rk4_scan', 'filter_scan', 'initial_state_innovations', 'sensitivity_scan'))


def signature(function):
    """Return the numba signature an exported kernel is compiled for."""
    from numba import typeof, types
    module, returns = EXPORTS[function]
    example = getattr(module, f'{function}_example')()
    return getattr(types, returns)(*(typeof(value) for value in example))


def _argument(numba_type):
    """Return one argument's description: [dtype, ndim, C-contiguous] (ndim 0: a scalar)."""
    from numba import types
    if isinstance(numba_type, types.Array):
        return [str(numba_type.dtype), numba_type.ndim, numba_type.layout == 'C']
    return [str(numba_type), 0, False]


def build_part(directory, name, functions):
    """
    Compile ``functions`` into the module ``directory/name``; return each one's argument types.

    Built in a temporary directory beside its destination and renamed there: another
    process never sees half a module.
    """
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')          # pycc's pending-deprecation notice
        from numba.pycc import CC, compiler

    class ReleasingFlags(compiler.Flags):
        """pycc's compile flags with the GIL released around each call (the kernels' nogil)."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    arguments = {}
    with tempfile.TemporaryDirectory(prefix='.kernels_build_', dir=directory) as work:
        compiler_flags, compiler.Flags = compiler.Flags, ReleasingFlags
        try:
            cc = CC(name)
            cc.output_dir = work
            cc.target_cpu = 'host'           # as the just-in-time kernels: this machine's CPU
            cc.verbose = False
            for function in functions:
                module, _ = EXPORTS[function]
                compiled_for = signature(function)
                arguments[function] = [_argument(a) for a in compiled_for.args]
                cc.export(function, compiled_for)(getattr(module, function).py_func)
            cc.compile()
        finally:
            compiler.Flags = compiler_flags
        built = next(Path(work).glob(f'{name}.*'))
        os.replace(built, Path(directory) / built.name)
    return arguments


def _build_part(job):
    """:func:`build_part` of one of :data:`PARTS` (a worker process): (module, argument types)."""
    directory, name, part = job
    return f'{name}_{part}', build_part(directory, f'{name}_{part}', PARTS[part])


def build(directory, name):
    """
    Compile every exported kernel: :data:`PARTS` in parallel, then ``directory/name.json``.

    The JSON maps each kernel to its module and argument types; it is written last (the loader
    looks for it), through a temporary file.
    """
    assert sorted(sum(PARTS, ())) == sorted(EXPORTS), 'every export in exactly one part'
    jobs = [(directory, name, part) for part in range(len(PARTS))]
    with multiprocessing.get_context('fork').Pool(len(PARTS)) as pool:
        built = pool.map(_build_part, jobs)
    described = {function: {'module': module, 'arguments': types}
                 for module, arguments in built for function, types in arguments.items()}
    target = Path(directory) / f'{name}.json'
    partial = target.with_suffix('.json.partial')
    partial.write_text(json.dumps(described))
    os.replace(partial, target)
    return target
