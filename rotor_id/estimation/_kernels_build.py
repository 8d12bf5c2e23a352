"""
Compile the numba kernels ahead of time (numba.pycc) into an extension module next to them.

Imported only from :func:`rotor_id.estimation.kernels.build_ahead_of_time` (``make build``). The
just-in-time kernels are warmed up first (their cache is the fallback), then every exported
kernel is compiled once more, for the one signature the warm-up gave it, into
``_kernels_aot_<key>`` with a JSON sidecar that lists each argument's type. The key hashes
the kernels' sources and the numba, numpy and Python versions, so a module built from other
sources is never found. The Python wrappers release the GIL as the ``nogil`` kernels do.
"""

import json
import os
from pathlib import Path
import tempfile
import warnings

from rotor_id.estimation import _filter_kernels_numba, _kernels_numba

#: the kernels :mod:`rotor_id.estimation.kernels` calls, by the module that defines them
EXPORTS = {'rk4_scan': _kernels_numba, 'filter_scan': _kernels_numba,
           'initial_state_innovations': _kernels_numba, 'affine_run': _kernels_numba,
           'gn_iteration': _kernels_numba, 'gn_fit': _kernels_numba,
           'clock_ns': _kernels_numba, 'sensitivity_scan': _filter_kernels_numba}


def _argument(numba_type):
    """Return one argument's description: [dtype, ndim, C-contiguous] (ndim 0: a scalar)."""
    from numba import types
    if isinstance(numba_type, types.Array):
        return [str(numba_type.dtype), numba_type.ndim, numba_type.layout == 'C']
    return [str(numba_type), 0, False]


def build(directory, name):
    """Compile the exported kernels into ``directory/name`` (+ ``name.json``); return its path."""
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')          # pycc's pending-deprecation notice
        from numba.pycc import CC, compiler

    class ReleasingFlags(compiler.Flags):
        """pycc's compile flags with the GIL released around each call (the kernels' nogil)."""

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    _kernels_numba.warm_up()
    _kernels_numba.warm_up_filter()
    _kernels_numba.warm_up_affine()
    _kernels_numba.warm_up_gn()
    _filter_kernels_numba.warm_up()
    arguments = {}
    # built beside its destination, then renamed there: another process never sees half a file
    with tempfile.TemporaryDirectory(prefix='.kernels_build_', dir=directory) as work:
        compiler_flags, compiler.Flags = compiler.Flags, ReleasingFlags
        try:
            cc = CC(name)
            cc.output_dir = work
            cc.target_cpu = 'host'           # as the just-in-time kernels: this machine's CPU
            cc.verbose = False
            for function, module in EXPORTS.items():
                dispatcher = getattr(module, function)
                signatures = list(dispatcher.overloads.values())
                if len(signatures) != 1:
                    raise RuntimeError(f'{function} has {len(signatures)} compiled signatures '
                                       '(one expected: its warm-up types)')
                signature = signatures[0].signature
                arguments[function] = [_argument(a) for a in signature.args]
                cc.export(function, signature)(dispatcher.py_func)
            cc.compile()
        finally:
            compiler.Flags = compiler_flags
        built = next(Path(work).glob(f'{name}.*'))
        (Path(work) / f'{name}.json').write_text(json.dumps(arguments))
        target = Path(directory) / built.name
        os.replace(Path(work) / f'{name}.json', Path(directory) / f'{name}.json')
        os.replace(built, target)            # last: the loader looks for the module
    return target
