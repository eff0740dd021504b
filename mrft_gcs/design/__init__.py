"""The offline design pipeline: how the bundled classifiers in ``models/`` are made.

Run by ``mrft-tune design`` (needs the ``design`` extra: torch, onnx, dask), never by a
live tune or a replay: the runtime (:mod:`mrft_gcs.identify`) reads only what this
pipeline wrote to ``models/`` and imports nothing from here.

Modules, in pipeline order:

- :mod:`~mrft_gcs.design.discretize`: discretisation into representative processes;
- :mod:`~mrft_gcs.design.phase`: distinguishing phase (Algorithm 1), zeta tables,
  cascade structure (Algorithm 2), rule costs;
- :mod:`~mrft_gcs.design.side`: side motion per attitude shape (Algorithm 3);
- :mod:`~mrft_gcs.design.dataset`: simulated, labelled relay cycles;
- :mod:`~mrft_gcs.design.train`: the classifier (torch), exported to ONNX;
- :mod:`~mrft_gcs.design.evaluate`: the evaluation over random processes (Table VI);
- :mod:`~mrft_gcs.design.pipeline`: the steps that write ``models/``;
- :mod:`~mrft_gcs.design.executor`: local processes or a Dask cluster.
"""

__all__: list[str] = []
