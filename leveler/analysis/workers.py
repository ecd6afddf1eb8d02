"""Worker processes of the analysis (null calibration runs, a round's effect families):
each fills a core of its own, so each keeps to one BLAS thread."""

from __future__ import annotations

import os

from threadpoolctl import threadpool_limits


def one_blas_thread() -> None:
    """For a worker process among others that fill the cores, and what it starts: BLAS
    threads of its own only fight over them (4 null runs on 2 cores: 31 s with them, 16 s
    without)."""
    os.environ.update(OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    threadpool_limits(1)
