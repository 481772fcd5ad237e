"""One BLAS/OpenMP/torch thread per process: the machine has 2 cores and the stages share them.

Entry points call `limit_threads()` first (launch.py, every `python -m` main, the benches); no module sets the
variables when imported. The variables reach the processes started afterwards and the libraries loaded
afterwards; threadpoolctl (installed with scikit-learn, which librosa needs) limits the BLAS numpy has
already loaded, and torch is pinned when it is loaded.
"""

import os
import sys

THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def limit_threads() -> None:
    for var in THREAD_VARIABLES:
        os.environ[var] = "1"
    if "numpy" in sys.modules:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)
