"""Runtime identification: latency (one cycle, CPU) and size of the bundled models."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from mrft_gcs.features import cycle_features
from mrft_gcs.identify import identify
from mrft_gcs.identify.runtime import MODELS_DIR, _softmax, load_bundle
from mrft_gcs.loops import LoopKind
from mrft_gcs.simulate import simulate_mrft


def main() -> None:
    total = sum(f.stat().st_size for f in Path(MODELS_DIR).rglob("*")
                if f.is_file() and f.suffix in (".onnx", ".json"))
    print(f"bundled models (onnx + tables): {total / 1e6:.2f} MB")
    for kind in (LoopKind.ATTITUDE, LoopKind.ALTITUDE):
        try:
            b = load_bundle(kind)
        except Exception as exc:  # noqa: BLE001
            print(f"{kind.value}: {exc}")
            continue
        run = simulate_mrft(1.0, b.shape_params[0, 0] * 0.5, 0.5, b.shape_params[0, 2] * 0.5,
                            beta=b.beta, h=b.h, duration_s=8.0)
        f = cycle_features(run.t, run.u[0], run.y[0])
        for what, fn in (("network only", lambda b=b, f=f: b.logits(f.x)),
                         ("features + network + gains", lambda b=b, run=run: _softmax(
                             b.logits(cycle_features(run.t[-3000:], run.u[0, -3000:],
                                                     run.y[0, -3000:]).x)[0]))):
            fn()
            t = []
            for _ in range(300):
                t0 = time.perf_counter()
                fn()
                t.append(time.perf_counter() - t0)
            t = np.array(t) * 1e3
            print(f"{kind.value} {what}: p50 {np.percentile(t, 50):.3f} ms, p99 "
                  f"{np.percentile(t, 99):.3f} ms")
        # the whole identification: features, network, harmonics, model fit, optimal PD
        t = []
        for _ in range(30):
            t0 = time.perf_counter()
            identify(kind, run.t[-3000:], run.u[0, -3000:], run.y[0, -3000:], beta=b.beta,
                     h=b.h)
            t.append(time.perf_counter() - t0)
        t = np.array(t) * 1e3
        print(f"{kind.value} identify() (harmonic fit + optimal PD): p50 "
              f"{np.percentile(t, 50):.1f} ms, max {t.max():.1f} ms")
    manifest = json.loads((Path(MODELS_DIR) / "manifest.json").read_text())
    for kind, steps in manifest.items():
        if isinstance(steps, dict) and "train" in steps:
            print(f"{kind}: training {steps['train']['seconds']:.0f} s, "
                  f"chose {steps['train']['config']}")


if __name__ == "__main__":
    main()
