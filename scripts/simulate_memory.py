"""Peak RSS and wall time of spindle.simulate on N samples of one spindle.

    python scripts/simulate_memory.py SOURCE_DIR N BACKEND     # e.g. . 1e6 numpy

SOURCE_DIR is put first on sys.path (a checkout of another revision measures that one); the
peak is the process's ru_maxrss, which includes the interpreter and numpy (~35 MB) and the
making of the input. Results: docs/spindle_accuracy.md, "Memory on long inputs".
"""

import resource
import sys
import time

if len(sys.argv) != 4 or sys.argv[1] in ("-h", "--help"):
    print(__doc__)
    sys.exit(0 if sys.argv[1:2] in (["-h"], ["--help"]) else 2)
sys.path.insert(0, sys.argv[1])
import numpy as np

import spindle

n, backend = int(float(sys.argv[2])), sys.argv[3]
t = np.arange(n) * 1e-3
L = 1.0 + 0.2 * np.sin(2 * np.pi * 0.5 * t)
del t
start = time.perf_counter()
r = spindle.simulate(L, 1e-3, gamma_dyn=70.0, gamma_stat=70.0, backend=backend)
wall = time.perf_counter() - start
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(f"{n:.0e} {backend}: peak RSS {peak:.0f} MB, input {L.nbytes/1e6:.0f} MB, {wall:.1f} s, "
      f"ia finite {np.isfinite(r.ia).all()}")
