"""Built-in benchmark systems (installed as ``kkl_bench.systems``)."""
