"""Coverage of 95% intervals of a mean at the seed counts RL experiments use: the percentile bootstrap the package
used before (``bootstrap_ci``, removed) against the Student-t interval it uses now (``mean_interval``), side by side;
and the coverage of the stratified-bootstrap IQM interval of ``experiments.aggregates`` over 5 tasks.

    python benchmarks/bench_intervals.py                    # about a minute on one core
    python benchmarks/bench_intervals.py --samples 20000    # the figures quoted in mean_interval's docstring

Coverage is the share of simulated samples whose interval contains the true mean (or the true IQM). Data: normal,
and moderately skewed (lognormal, sigma 0.5); each sample is n values, as n seeds of one condition.
"""
import argparse
import time

import numpy as np

from torchrl_options.experiments.aggregates import _iqm, stratified_bootstrap_interval
from torchrl_options.experiments.intervals import t_intervals

DISTRIBUTIONS = {
    # name: (sampler(rng, shape), true mean)
    "normal": (lambda rng, shape: rng.normal(0.0, 1.0, shape), 0.0),
    "lognormal, sigma 0.5": (lambda rng, shape: rng.lognormal(0.0, 0.5, shape), float(np.exp(0.125))),
}


def percentile_bootstrap_coverage(x: np.ndarray, true_mean: float, resamples: int, rng, confidence=0.95) -> float:
    """What the old ``bootstrap_ci`` did, for each row of ``x`` ``[samples, n]``: the percentile interval of the
    means of ``resamples`` resamples drawn with replacement."""
    alpha = (1 - confidence) / 2
    hits = 0
    for start in range(0, x.shape[0], 200):
        chunk = x[start : start + 200]
        idx = rng.integers(0, chunk.shape[1], size=(chunk.shape[0], resamples, chunk.shape[1]))
        means = np.take_along_axis(chunk[:, None, :].repeat(resamples, 1), idx, axis=2).mean(-1)
        lo, hi = np.quantile(means, alpha, axis=1), np.quantile(means, 1 - alpha, axis=1)
        hits += int(((lo <= true_mean) & (true_mean <= hi)).sum())
    return hits / x.shape[0]


def t_coverage(x: np.ndarray, true_mean: float, confidence=0.95) -> float:
    _, lo, hi = t_intervals(x, confidence, axis=1)
    return float(((lo <= true_mean) & (true_mean <= hi)).mean())


def iqm_coverage(sampler, n: int, tasks: int, samples: int, resamples: int, rng) -> float:
    """Coverage of the stratified-bootstrap IQM interval; task t's runs are ``sampler + t`` (tasks differ)."""
    shift = np.arange(tasks, dtype=float)
    population = sampler(rng, (400_000, tasks)) + shift
    true_iqm = float(_iqm(population))
    hits = 0
    for i in range(samples):
        x = sampler(rng, (n, tasks)) + shift
        _, lo, hi = stratified_bootstrap_interval(_iqm, x, num_resamples=resamples, seed=i)
        hits += bool(lo <= true_iqm <= hi)
    return hits / samples


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--samples", type=int, default=4000, help="simulated samples per case")
    p.add_argument("--resamples", type=int, default=1000, help="bootstrap resamples of the old interval")
    p.add_argument("--ns", default="3,5,8,15")
    p.add_argument("--aggregate-samples", type=int, default=300, help="samples per case of the IQM table (0: skip)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    ns = [int(n) for n in args.ns.split(",")]
    rng = np.random.default_rng(args.seed)
    start = time.perf_counter()
    print(f"Coverage of nominal 95% intervals of the mean, {args.samples} samples per case\n")
    print("| data | n | percentile bootstrap (old `bootstrap_ci`) | Student-t (`mean_interval`) |")
    print("|---|---|---|---|")
    for name, (sampler, true_mean) in DISTRIBUTIONS.items():
        for n in ns:
            x = sampler(rng, (args.samples, n))
            old = percentile_bootstrap_coverage(x, true_mean, args.resamples, rng)
            new = t_coverage(x, true_mean)
            print(f"| {name} | {n} | {old:.3f} | {new:.3f} |")
    if args.aggregate_samples:
        print(f"\nCoverage of the 95% stratified-bootstrap IQM interval over 5 tasks (`experiments.aggregates`), "
              f"{args.aggregate_samples} samples per case, 500 resamples\n")
        print("| data | runs per task | coverage |")
        print("|---|---|---|")
        for name, (sampler, _) in DISTRIBUTIONS.items():
            for n in ns[:3]:
                cov = iqm_coverage(sampler, n, 5, args.aggregate_samples, 500, rng)
                print(f"| {name} | {n} | {cov:.3f} |")
    print(f"\n{time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
