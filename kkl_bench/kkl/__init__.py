"""KKL toolkit: the machinery every KKL-type estimator plugin shares.

- :mod:`.latent`: the linear latent observer ``dz/dt = A z + B y (+ injection)``
  integrated exactly between samples (matrix exponential, first-order hold).
- :mod:`.networks`: normalized encoder ``T(x)`` and decoder ``T*(z)`` MLPs,
  with a batched forward under per-window weight perturbations.
- :mod:`.pde`: the KKL PDE residual by Jacobian-vector product.
- :mod:`.data`: (state, latent) training pairs from the observer itself.
- :mod:`.windows`: sliding input windows and their LSTM embedding.
- :mod:`.hyper`: hypernetwork heads (chunked full-rank, low-rank).
- :mod:`.cache`: content-keyed checkpoint cache.
- :mod:`.autonomous`: Phase 1, the autonomous observer every plugin starts from.

Layer: above the fitting helpers, the plugin face, support, the suite and the protocol;
the estimators and the learning face build on it.
"""
