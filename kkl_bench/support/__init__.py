"""What the estimators and the runs lean on, knowing nothing of either: the model and
kernel caches, devices, threads and job execution, flop counting, the convergence
verdicts, the status files of running jobs and the provenance of the code.

Layer: imports nothing of kkl_bench but the protocol."""
