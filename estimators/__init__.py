"""Built-in estimator plugins (installed as ``kkl_bench.estimators``): :mod:`.filters`, the
model-based rows and their kernels; :mod:`.learned`, the learned observers.

Layer: above the KKL toolkit, fitting, the plugin face and support; never the run layer."""
