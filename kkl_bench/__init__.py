"""kkl-bench: a benchmark suite for state observers of nonlinear systems driven by inputs.

The package root holds what a plugin author imports: :mod:`.estimator` (the base class
and the fit context), :mod:`.registry`, :mod:`.families`, :mod:`.variants`,
:mod:`.training` (training data), :mod:`.learning` (how a learned plugin trains),
:mod:`.measurement` and :mod:`.testing` (the conformance kits). Below it the layers,
each importing only those under it (``tests/test_layers.py`` checks the contracts of
``pyproject.toml``'s ``[tool.importlinter]``), from the bottom:

- :mod:`.protocol`: the math every number rests on (systems, signals, RK4, streams,
  metrics);
- :mod:`.measurement`, :mod:`.registry`; the plugin folders ``kkl_bench.systems`` and
  ``kkl_bench.tasks``;
- :mod:`.suite`: how a task is defined (tracks, tasks and profiles, plants);
  :mod:`.support`: what estimators and runs lean on (caches, devices, threads,
  convergence, status, provenance);
- the plugin face (:mod:`.training`, :mod:`.estimator`, :mod:`.variants`,
  :mod:`.families`);
- :mod:`.fitting`: what fits share (settings chosen on validation streams, the model
  calibrated on logged data); :mod:`.kkl`: the KKL toolkit;
- ``kkl_bench.estimators`` (filters and learned observers), :mod:`.learning`;
- :mod:`.run`: how a run executes and stores cells; :mod:`.testing`;
- :mod:`.analysis`: how stored cells are analysed; :mod:`.report`: the published board;
  :mod:`.cli`: the command line.
"""
