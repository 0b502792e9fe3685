"""Built-in estimator plugins (installed as ``kkl_bench.estimators``)."""
