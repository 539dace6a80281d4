"""Command-line tools (thin adapters over the core).

The numerical core solves many small dense systems; multi-threaded BLAS only thrashes on them (measured
20x slower on 2 cores under load), so the tools default to one BLAS thread unless the user says otherwise.
This must happen before numpy is first imported, hence here.
"""

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
