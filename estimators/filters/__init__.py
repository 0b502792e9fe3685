"""The model-based rows: EKF and UKF (filterpy and compiled engines), the ensemble filter
and the particle-filter limit, with their compiled kernels."""
