"""Classifier training and ONNX export (the ``design`` extra: torch, onnx).

Fully connected networks with batch norm and dropout after each hidden layer,
trained with Adam on the cost-augmented soft-max of eq. 19: the logit of each
class ``j`` is multiplied by ``1 + J_jT`` (the joint cost between class ``j``
and the row's true region ``T``, as a fraction), so confusing costly classes
is penalised more. A small search over depth, width and activation (Table IV)
keeps the network with the lowest validation cost; the loss itself (eq. 19 or
plain cross-entropy) is part of that search, because on these shape classes the
augmented loss measured worse. At run time the plain soft-max of the exported
logits is used. The runtime never imports this module.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mrft_gcs.design.dataset import Dataset
from mrft_gcs.errors import MissingDependency

__all__ = ["TrainResult", "train_classifier", "export_onnx", "SEARCH_SPACE"]

#: Table IV-style search space (depth, width, activation, loss), kept small for a 2-core
#: machine; "eq19" is the cost-augmented soft-max, "ce" plain cross-entropy.
SEARCH_SPACE = [(2, 256, "relu", "ce"), (2, 256, "relu", "eq19"), (3, 256, "relu", "ce"),
                (2, 256, "tanh", "ce")]


def _torch():
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise MissingDependency(
            "training needs torch: pip install torch==2.13.0 && pip install -e '.[design]'"
        ) from exc
    return torch


@dataclass(frozen=True)
class TrainResult:
    """The chosen network and how it was chosen."""

    model: object
    config: tuple
    val_accuracy: float
    val_mean_J: float
    search: list[dict]
    seconds: float
    mean: np.ndarray
    std: np.ndarray
    temperature: float = 1.0


def _build(torch, n_in: int, n_out: int, depth: int, width: int, act: str, dropout: float):
    nn = torch.nn
    layers: list = []
    d = n_in
    for _ in range(depth):
        layers += [nn.Linear(d, width), nn.BatchNorm1d(width),
                   nn.ReLU() if act == "relu" else nn.Tanh(), nn.Dropout(dropout)]
        d = width
    layers.append(nn.Linear(d, n_out))
    return nn.Sequential(*layers)


def train_classifier(train: Dataset, val: Dataset, n_classes: int, seed: int = 0,
                     epochs: int = 60, search=SEARCH_SPACE, progress=None) -> TrainResult:
    """Search the configurations and return the best network (lowest validation mean J)."""
    torch = _torch()
    torch.manual_seed(seed)
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    mean = train.x.mean(axis=0)
    std = train.x.std(axis=0) + 1e-6
    X = torch.tensor((train.x - mean) / std, dtype=torch.float32)
    Y = torch.tensor(train.label, dtype=torch.long)
    Jt = torch.tensor(np.minimum(train.J, 200.0) / 100.0, dtype=torch.float32)
    Xv = torch.tensor((val.x - mean) / std, dtype=torch.float32)
    Jv = np.minimum(val.J, 200.0)
    results = []
    best = None
    for config in search:
        depth, width, act = config[:3]
        loss_kind = config[3] if len(config) > 3 else "eq19"
        torch.manual_seed(seed)
        net = _build(torch, X.shape[1], n_classes, depth, width, act, dropout=0.1)
        opt = torch.optim.Adam(net.parameters(), lr=5e-3, betas=(0.9, 0.999))
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
        gen = torch.Generator().manual_seed(seed)
        for _epoch in range(epochs):
            net.train()
            perm = torch.randperm(len(X), generator=gen)
            for k in range(0, len(X), 256):
                b = perm[k:k + 256]
                if len(b) < 2:
                    continue
                logits = net(X[b])
                if loss_kind == "eq19":
                    logits = logits * (1.0 + Jt[b])  # cost-augmented soft-max
                loss = torch.nn.functional.cross_entropy(logits, Y[b])
                opt.zero_grad()
                loss.backward()
                opt.step()
            sched.step()
        net.eval()
        with torch.no_grad():
            pred = net(Xv).argmax(dim=1).numpy()
        acc = float(np.mean(pred == val.label))
        mean_J = float(np.mean(Jv[np.arange(len(pred)), pred]))
        results.append({"depth": depth, "width": width, "activation": act, "loss": loss_kind,
                        "val_accuracy": acc, "val_mean_J": mean_J})
        if progress:
            progress(len(results), len(search))
        if best is None or mean_J < best[1]:
            best = (net, mean_J, acc, tuple(config))
    assert best is not None
    # Temperature scaling on the validation set: honest probabilities for the Bayes
    # choice of gains at run time.
    with torch.no_grad():
        logits = best[0](Xv).numpy().astype(float)
    temps = np.exp(np.linspace(np.log(0.3), np.log(10.0), 60))
    nll = [_nll(logits / T, val.label) for T in temps]
    return TrainResult(best[0], best[3], best[2], best[1], results, time.perf_counter() - t0,
                       mean.astype(np.float32), std.astype(np.float32),
                       float(temps[int(np.argmin(nll))]))


def _nll(logits: np.ndarray, label: np.ndarray) -> float:
    z = logits - logits.max(axis=1, keepdims=True)
    logp = z - np.log(np.exp(z).sum(axis=1, keepdims=True))
    return float(-np.mean(logp[np.arange(len(label)), label]))


def export_onnx(result: TrainResult, path: Path) -> None:
    """Write the network, with the input standardisation folded in, as ONNX (opset 17)."""
    _torch()  # a missing torch raises MissingDependency naming the extra
    import torch

    mean = torch.tensor(result.mean)
    std = torch.tensor(result.std)

    class Wrapped(torch.nn.Module):
        def __init__(self, net):
            super().__init__()
            self.net = net
            self.register_buffer("mean", mean)
            self.register_buffer("std", std)

        def forward(self, x):
            return self.net((x - self.mean) / self.std)

    model = Wrapped(result.model).eval()
    example = torch.zeros(1, len(result.mean), dtype=torch.float32)
    torch.onnx.export(model, (example,), str(path), input_names=["x"], output_names=["logits"],
                      dynamic_axes={"x": {0: "batch"}, "logits": {0: "batch"}}, opset_version=17,
                      dynamo=False)


def write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=1))
