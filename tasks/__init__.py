"""Built-in input regimes and the task profiles (installed as ``kkl_bench.tasks``)."""
