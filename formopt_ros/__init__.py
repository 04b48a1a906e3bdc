"""formopt_ros: optimized follower motion for localization in leader-follower formations."""
import os

#: The environment variables that set the BLAS and OpenMP thread counts of NumPy and SciPy.
BLAS_THREAD_VARIABLES = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS')


def one_blas_thread() -> None:
    """Let NumPy run on one BLAS thread unless the environment sets a count (only effective
    before NumPy is first imported). The package's commands and nodes call it: SciPy's SLSQP in
    PERIODIC's designs ends at digits that depend on the thread count, so a study's numbers
    would depend on ``--jobs`` (Dask's workers run one thread each); its matrices are 3x3 to
    6x6, where threads gain nothing."""
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, '1')
