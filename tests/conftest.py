"""Suite-wide settings."""
import os

#: Thread pools of the numerical libraries (OpenBLAS, MKL's PARDISO, OpenMP, numba), one thread each in every
#: test worker: the default suite runs one worker per core (``pytest -n 2`` on 2 cores), where a second thread per
#: worker finds no free core.  A cold 0.4 mm inclusion forward solve took 13.1 s of CPU with 2 threads against
#: 9.9 s with one, in the same wall time.
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def pytest_configure(config):
    # only under pytest-xdist (the controller sets them before it starts the workers, which inherit them); a
    # variable set by the caller is kept
    if getattr(config.option, "numprocesses", None):
        for name in THREAD_VARIABLES:
            os.environ.setdefault(name, "1")
