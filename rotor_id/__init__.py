"""rotor_id: identification of rotor blade flapping dynamics (ROS 2 Jazzy, Python)."""

import os

#: One BLAS/LAPACK thread unless the user chose otherwise. Every matrix this package factors is
#: small (the initial-state least squares is a few thousand rows by ~10 columns) and its
#: parallelism is processes (diagnose, campaign, Monte Carlo); OpenBLAS's second thread only
#: waits on such sizes (bench/results/blas_threads.md: a least squares of that size, one thread
#: against two on a loaded machine). The variables act only if set before numpy loads
#: OpenBLAS, so they are set on importing this package (which the CLI and nodes import first)
#: and pass on to child processes.
BLAS_THREAD_VARIABLES = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')
for _name in BLAS_THREAD_VARIABLES:
    os.environ.setdefault(_name, '1')
del _name
