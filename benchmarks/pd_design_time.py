"""Optimal PD design time per process (ISE, PM >= 20 deg, Nelder-Mead), single core."""

from __future__ import annotations

import time

import numpy as np

from mrft_gcs.domains import D_ALT, D_ATT
from mrft_gcs.pd_design import frequency_grid, optimal_pd
from mrft_gcs.plant import inner_response


def main() -> None:
    for dom in (D_ATT, D_ALT):
        p = dom.sample_log_uniform(40, np.random.default_rng(0))
        times, evals = [], []
        for Tp, T1, tau in p:
            t = time.perf_counter()
            w = frequency_grid(Tp, T1, tau, n=600)
            d = optimal_pd(inner_response(1.0, Tp, T1, tau, w)[0], w)
            times.append(time.perf_counter() - t)
            evals.append(d.evaluations)
        t = np.array(times) * 1e3
        print(f"{dom.name}: {len(t)} designs, median {np.median(t):.0f} ms, p90 "
              f"{np.percentile(t, 90):.0f} ms, median {np.median(evals):.0f} cost evaluations")


if __name__ == "__main__":
    main()
