"""Throughput of patch_roughness(_batch) against a straightforward per-profile loop.

Run: ``python benchmarks/bench_psd.py [--patches 400]``

Both run in this process on the same 112 x 112 patches, on one core (BLAS threads are
limited to 1), and the figure that matters is their ratio: machines here are noisy.
The baseline is what one would write first: for each profile, ``scipy.signal.welch``
(Hann, one segment, linear detrend) and ``numpy.polyfit`` in log-log, then the patch
mean.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from scipy import signal
from threadpoolctl import threadpool_limits

from rough_map.iso8608 import synthesize_surface
from rough_map.psd import patch_roughness, patch_roughness_batch

B = 0.008


def baseline(h: np.ndarray) -> tuple[float, float]:
    """Per-profile welch + polyfit (the paper's method, written plainly)."""
    lnr, ws = [], []
    for row in h:
        f, p = signal.welch(row, fs=1 / B, window="hann", nperseg=row.size, detrend="linear")
        omega, phi = 2 * np.pi * f[1:], p[1:] / (2 * np.pi)
        w, b = np.polyfit(np.log(omega), np.log(phi), 1)
        lnr.append(b)
        ws.append(w)
    return math.exp(np.mean(lnr)), float(np.mean(ws))


def best_rate(fn, n_items: int, repeats: int) -> float:
    best = math.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return n_items / best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patches", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    stack = np.stack(
        [
            synthesize_surface((112, 112), B, "E", -2.4, seed=rng)
            for _ in range(min(args.patches, 64))
        ]
    )
    stack = np.concatenate([stack] * math.ceil(args.patches / len(stack)))[: args.patches]
    with threadpool_limits(1):
        patch_roughness_batch(stack[:4], B)  # warm caches (window, tables)
        batch = best_rate(lambda: patch_roughness_batch(stack, B), len(stack), args.repeats)
        single = best_rate(lambda: [patch_roughness(s, B) for s in stack], len(stack), args.repeats)
        n_base = min(len(stack), 40)
        base = best_rate(lambda: [baseline(s) for s in stack[:n_base]], n_base, 2)
    for label, rate in (
        (f"patch_roughness_batch (one call, {len(stack)} patches):", batch),
        ("patch_roughness, one call per patch:", single),
        ("baseline, welch + polyfit per profile:", base),
    ):
        print(f"{label:<51}{rate:10.0f} patches/s")
    print(f"ratio batched / baseline:    {batch / base:6.0f} x")
    print(f"ratio per-patch / baseline:  {single / base:6.0f} x")


if __name__ == "__main__":
    main()
