"""The offline design pipeline behind ``models/`` (``mrft-tune design ...``).

Steps per inner loop kind (attitude, altitude), each reading the previous
step's output from ``models/<kind>/`` and recording what it did in
``models/manifest.json`` (inputs, code version, seed, wall time):

1. ``discretize`` -> ``discretisation.json``  (representative processes)
2. ``phase``      -> ``phase.json``           (distinguishing phase, Algorithm 1)
3. ``zeta``       -> ``zeta.json``            (unit cycles and exact gain scaling)
4. ``dataset``    -> ``dataset_{train,val}.npz`` (not committed: regenerated from the seed)
5. ``train``      -> ``classifier.onnx`` + ``classes.json`` (needs the ``design`` extra)
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np

from mrft_gcs.design.dataset import Dataset, make_dataset
from mrft_gcs.design.discretize import (
    Discretisation,
    _grid_for,
    discretize_inner,
    reachable_scales,
)
from mrft_gcs.design.executor import make_executor
from mrft_gcs.design.phase import (
    BETA_GRID,
    distinguishing_phase,
    rule_cost_table,
    unit_cycles,
    zeta_table,
)
from mrft_gcs.design.side import design_side_for_shape, side_dataset_realistic
from mrft_gcs.design.train import SEARCH_SPACE, export_onnx, train_classifier
from mrft_gcs.domains import domain_for
from mrft_gcs.errors import UsageError
from mrft_gcs.identify.runtime import MODELS_DIR
from mrft_gcs.loops import LoopKind

__all__ = [
    "MODELS_DIR",
    "step_discretize",
    "step_phase",
    "step_zeta",
    "step_dataset",
    "load_json",
    "load_dataset",
    "record",
    "INNER_KINDS",
]

INNER_KINDS = (LoopKind.ATTITUDE, LoopKind.ALTITUDE)

#: Default relay amplitudes per loop kind (paper Table V): attitude 5 % of the
#: largest moment, altitude 10.746 % of full thrust.
DEFAULT_H = {LoopKind.ATTITUDE: 0.05, LoopKind.ALTITUDE: 0.10746}


def _code_version() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, cwd=Path(__file__).parent, timeout=5).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _dir(kind: LoopKind, models: Path) -> Path:
    d = models / kind.value
    d.mkdir(parents=True, exist_ok=True)
    return d


def load_json(kind: LoopKind, name: str, models: Path = MODELS_DIR) -> dict:
    """A step's output; a clear error naming the step to run when it is missing."""
    path = models / kind.value / f"{name}.json"
    if not path.exists():
        step = {"discretisation": "discretize"}.get(name, name)
        raise UsageError(f"{path} is missing: run 'mrft-tune design {step} --loop "
                         f"{kind.value}' first")
    return json.loads(path.read_text())


def record(models: Path, kind: LoopKind, step: str, info: dict) -> None:
    """Add a step's entry to ``models/manifest.json``."""
    path = models / "manifest.json"
    manifest: dict[str, Any] = (json.loads(path.read_text()) if path.exists()
                                else {"schema": "mrft-gcs-models/1"})
    manifest.setdefault(kind.value, {})[step] = {
        **info, "code_version": _code_version(), "finished": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    path.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def _check_inner(kind: LoopKind) -> None:
    if kind not in INNER_KINDS:
        raise UsageError("this step is for --loop attitude or altitude (side motion has its own)")


def step_discretize(kind: LoopKind, models: Path = MODELS_DIR, J_target: float = 10.0,
                    tolerance: float = 3.0, grid_n: int = 16, progress=None) -> Discretisation:
    _check_inner(kind)
    t0 = time.perf_counter()
    disc = discretize_inner(domain_for(kind), J_target, tolerance, grid_n=grid_n,
                            progress=progress)
    (_dir(kind, models) / "discretisation.json").write_text(json.dumps(disc.to_json()))
    record(models, kind, "discretize", {
        "J_target": J_target, "tolerance": tolerance, "grid_n": grid_n,
        "shapes": len(disc.shapes), "representatives": len(disc.reps),
        "seconds": time.perf_counter() - t0,
    })
    return disc


def _shape_params(disc: Discretisation) -> np.ndarray:
    return np.column_stack([np.exp(disc.shapes[:, 0]), np.ones(len(disc.shapes)),
                            np.exp(disc.shapes[:, 1])])


def step_phase(kind: LoopKind, models: Path = MODELS_DIR) -> dict:
    _check_inner(kind)
    t0 = time.perf_counter()
    disc = Discretisation.from_json(load_json(kind, "discretisation", models))
    params = _shape_params(disc)
    cyc = unit_cycles(params, BETA_GRID)
    res = distinguishing_phase(params, disc.shape_pd, disc.shape_ise, cyc, _grid_for(disc.shapes))
    out = {
        "beta": res.beta, "phase_deg": res.phase_deg, "betas": res.betas.tolist(),
        "worst_J": [float(x) for x in res.worst_J], "rule_index": res.rule_index,
        "c1": res.c1, "c2": res.c2,
        "unit_period": cyc.period.tolist(), "unit_amplitude": cyc.amplitude.tolist(),
    }
    (_dir(kind, models) / "phase.json").write_text(json.dumps(out))
    record(models, kind, "phase", {"beta": res.beta, "phase_deg": res.phase_deg,
                                   "worst_J": float(np.min(res.worst_J)),
                                   "seconds": time.perf_counter() - t0})
    return out


def step_zeta(kind: LoopKind, models: Path = MODELS_DIR) -> dict:
    _check_inner(kind)
    t0 = time.perf_counter()
    disc = Discretisation.from_json(load_json(kind, "discretisation", models))
    beta = load_json(kind, "phase", models)["beta"]
    params = _shape_params(disc)
    # Finer than the phase scan: more cycles, finer step, at the chosen beta only.
    cyc = unit_cycles(params, [beta], cycles=20, dt_frac=5e-5)
    period, amp = cyc.period[:, 0], cyc.amplitude[:, 0]
    zeta = zeta_table(params, period, amp)
    cost = rule_cost_table(params, disc.shape_pd, disc.shape_ise, period, amp,
                           _grid_for(disc.shapes))
    out = {"beta": beta, "unit_period": period.tolist(), "unit_amplitude": amp.tolist(),
           "zeta": zeta.tolist(), "zeta_df": 4 / np.pi,
           "rule_cost": np.where(np.isfinite(cost), cost, 1e6).tolist()}
    (_dir(kind, models) / "zeta.json").write_text(json.dumps(out))
    record(models, kind, "zeta", {"zeta_min": float(zeta.min()), "zeta_max": float(zeta.max()),
                                  "seconds": time.perf_counter() - t0})
    return out


def step_dataset(kind: LoopKind, models: Path = MODELS_DIR, n_train: int = 6000,
                 n_val: int = 2000, seed: int = 0, progress=None) -> tuple[Dataset, Dataset]:
    _check_inner(kind)
    t0 = time.perf_counter()
    disc = Discretisation.from_json(load_json(kind, "discretisation", models))
    z = load_json(kind, "zeta", models)
    args = (disc, domain_for(kind), z["beta"], np.asarray(z["unit_period"]),
            np.asarray(z["unit_amplitude"]))
    train = make_dataset(*args, n=n_train, seed=seed, progress=progress)
    val = make_dataset(*args, n=n_val, seed=seed + 1, progress=progress)
    d = _dir(kind, models)
    for name, ds in (("train", train), ("val", val)):
        np.savez_compressed(d / f"dataset_{name}.npz", **{k: getattr(ds, k) for k in
                                                          Dataset.__dataclass_fields__})
    record(models, kind, "dataset", {"n_train": len(train), "n_val": len(val), "seed": seed,
                                     "seconds": time.perf_counter() - t0})
    return train, val


def load_dataset(kind: LoopKind, name: str, models: Path = MODELS_DIR) -> Dataset:
    path = models / kind.value / f"dataset_{name}.npz"
    if not path.exists():
        raise UsageError(f"{path} is missing: run 'mrft-tune design dataset --loop {kind.value}'")
    with np.load(path) as z:
        return Dataset(**{k: z[k] for k in Dataset.__dataclass_fields__})


def step_train(kind: LoopKind, models: Path = MODELS_DIR, seed: int = 0, epochs: int = 60,
               search=None, progress=None) -> dict:
    """Train, export ``classifier.onnx`` and write the runtime class table ``classes.json``."""
    _check_inner(kind)
    t0 = time.perf_counter()
    disc = Discretisation.from_json(load_json(kind, "discretisation", models))
    z = load_json(kind, "zeta", models)
    train, val = load_dataset(kind, "train", models), load_dataset(kind, "val", models)
    res = train_classifier(train, val, len(disc.shapes), seed=seed, epochs=epochs,
                           search=search or SEARCH_SPACE, progress=progress)
    d = _dir(kind, models)
    export_onnx(res, d / "classifier.onnx")
    table = {
        "schema": "mrft-gcs-classes/1", "kind": kind.value, "beta": z["beta"],
        "h": DEFAULT_H[kind], "shape_params": _shape_params(disc).tolist(),
        "shape_pd": disc.shape_pd.tolist(), "unit_period": z["unit_period"],
        "unit_amplitude": z["unit_amplitude"], "zeta": z["zeta"], "reps": disc.reps.tolist(),
        "rule_cost": z["rule_cost"], "temperature": res.temperature,
        "rep_shape": disc.rep_shape.tolist(), "input": "features.cycle_features v1",
    }
    (d / "classes.json").write_text(json.dumps(table))
    info = {"config": list(res.config), "val_accuracy": res.val_accuracy,
            "temperature": res.temperature,
            "val_mean_J": res.val_mean_J, "search": res.search, "epochs": epochs, "seed": seed,
            "seconds": time.perf_counter() - t0,
            "onnx_bytes": (d / "classifier.onnx").stat().st_size}
    record(models, kind, "train", info)
    return info


def _side_task(args: tuple) -> dict:
    """Design, data and classifier for one attitude shape (a picklable executor task)."""
    k, att, att_pd, lo, hi, grid_n, n_rows, seed, out_dir, train = args
    sc = design_side_for_shape(k, np.asarray(att), np.asarray(att_pd), lo, hi, grid_n=grid_n)
    d = Path(out_dir) / f"shape_{k:02d}"
    d.mkdir(parents=True, exist_ok=True)
    (d / "classes.json").write_text(json.dumps({**sc.to_json(), "scale_lo": lo, "scale_hi": hi}))
    info = {"shape": k, "classes": len(sc.params), "beta": sc.beta, "worst_J": sc.worst_J,
            "zeta_min": float(sc.zeta.min()), "zeta_max": float(sc.zeta.max()),
            "design_s": sc.seconds}
    if train:
        disc = Discretisation.from_json(load_json(LoopKind.ATTITUDE, "discretisation",
                                                  Path(out_dir).parent))
        tr = side_dataset_realistic(sc, disc, n_rows, seed + 2 * k)
        va = side_dataset_realistic(sc, disc, n_rows // 3, seed + 2 * k + 1)
        res = train_classifier(tr, va, len(sc.params), seed=seed, epochs=40,
                               search=[(2, 128, "relu", "ce")])
        export_onnx(res, d / "classifier.onnx")
        table = json.loads((d / "classes.json").read_text())
        table["temperature"] = res.temperature
        (d / "classes.json").write_text(json.dumps(table))
        info.update({"rows": len(tr), "val_accuracy": res.val_accuracy,
                     "val_mean_J": res.val_mean_J, "train_s": res.seconds})
    return info


def step_side(models: Path = MODELS_DIR, grid_n: int = 6, n_rows: int = 900, seed: int = 0,
              workers: int = 1, dask: str | None = None, train: bool = True,
              shapes: list[int] | None = None) -> list[dict]:
    """Algorithm 3 for every attitude shape: side classes, phase, zeta, data and classifier."""
    t0 = time.perf_counter()
    disc = Discretisation.from_json(load_json(LoopKind.ATTITUDE, "discretisation", models))
    dom = domain_for(LoopKind.ATTITUDE)
    out = _dir(LoopKind.SIDE, models)
    tasks = []
    for k in shapes if shapes is not None else range(len(disc.shapes)):
        own = np.flatnonzero(disc.cand_owner == k)
        lo, hi = reachable_scales(dom, disc.cand_shapes[own, 0], disc.cand_shapes[own, 1])
        ok = lo <= hi
        if not ok.any():  # the shape's region holds no reachable candidate: use its own range
            lo, hi = reachable_scales(dom, disc.shapes[k:k + 1, 0], disc.shapes[k:k + 1, 1])
            ok = np.ones(1, bool)
        lo_k, hi_k = float(lo[ok].min()), float(max(hi[ok].max(), lo[ok].min()))
        att = [float(np.exp(disc.shapes[k, 0])), 1.0, float(np.exp(disc.shapes[k, 1]))]
        tasks.append((k, att, disc.shape_pd[k].tolist(), lo_k, hi_k, grid_n, n_rows, seed,
                      str(out), train))
    with make_executor(workers, dask) as ex:
        infos = ex.map(_side_task, tasks)
    record(models, LoopKind.SIDE, "side", {"grid_n": grid_n, "rows": n_rows, "seed": seed,
                                           "per_shape": infos,
                                           "seconds": time.perf_counter() - t0})
    return infos
