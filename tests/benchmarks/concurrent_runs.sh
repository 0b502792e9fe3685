#!/usr/bin/env bash
# The README's quick job (4 fits of dynamic_hyperkkl) timed alone, two runs at once and
# with --jobs 2, on one thread a job (the default) and on two (torch's default before).
# Each run trains from its own empty model cache (the compiled filter kernels copied in
# from $KKL_BENCH_CACHE, so that no run pays numba's compilation). Prints one line per
# run: label and seconds. Run it from the repository root with the environment active.
set -u
scratch=$(mktemp -d)
kernels=${KKL_BENCH_CACHE:-.kkl_bench_cache}
trap 'rm -rf "$scratch"' EXIT
timed() {  # label, then arguments of kkl-bench run
    local label=$1 start
    shift
    mkdir -p "$scratch/$label"
    cp -r "$kernels"/bound_kernels "$kernels"/unrolled_kernels "$scratch/$label"/ 2>/dev/null
    start=$(date +%s.%N)
    KKL_BENCH_CACHE="$scratch/$label" kkl-bench run --estimator dynamic_hyperkkl \
        --results "$scratch/$label/results" "$@" >/dev/null 2>&1
    echo "$label $(echo "$(date +%s.%N) - $start" | bc)"
}
for threads in 1 2; do
    timed "alone-threads$threads" --threads "$threads"
    timed "pair-a-threads$threads" --threads "$threads" &
    timed "pair-b-threads$threads" --threads "$threads" &
    wait
done
timed "jobs2-threads1" --jobs 2
