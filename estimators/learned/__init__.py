"""The learned rows: the paper's KKL observers, the injection KKL observer, the GRU
observer, KalmanNet and the ring observer."""
