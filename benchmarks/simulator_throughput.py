"""MRFT simulator throughput: simulated process-seconds per wall second, single core.

Prints figures for the compiled kernel (numba) and the numpy reference, with and
without measurement noise, at the default 1 ms step. Run: python benchmarks/simulator_throughput.py
"""

from __future__ import annotations

import platform
import time

import numpy as np

from mrft_gcs import _kernels
from mrft_gcs.domains import D_ATT
from mrft_gcs.simulate import simulate_mrft


def rate(engine: str, n: int, duration: float, noise: float) -> float:
    rng = np.random.default_rng(0)
    p = D_ATT.sample_log_uniform(n, rng)
    kw = dict(beta=-0.5, h=1.0, duration_s=duration, keep_s=1.0, noise_std=noise, band=4 * noise,
              seed=1, engine=engine)
    simulate_mrft(1.0, *p[:4].T, **{**kw, "duration_s": 0.1})  # compile / warm up
    t = time.perf_counter()
    simulate_mrft(1.0, *p.T, **kw)
    return n * duration / (time.perf_counter() - t)


def main() -> None:
    print(f"machine: {platform.processor() or platform.machine()}, "
          f"python {platform.python_version()}")
    engines = ["numba", "numpy"] if _kernels.AVAILABLE else ["numpy"]
    for engine in engines:
        n = 2000 if engine == "numba" else 500
        for noise in (0.0, 1e-3):
            r = rate(engine, n, 10.0, noise)
            print(f"{engine:5s} n={n:5d} noise={noise:g}: {r:12,.0f} simulated process-s "
                  f"per wall s")


if __name__ == "__main__":
    main()
