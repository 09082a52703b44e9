"""Batch path versus a loop over runs: 2-D constant velocity, 1000 Monte Carlo runs x 1000 steps.

Both sides use the same public function, kftrack.kalman.kalman_filter:
* batch: one call with zs of shape (1000 steps, 1000 runs, 2): one broadcast update and
  predict per step for all runs;
* loop: one call per run, zs of shape (1000 steps, 2).
The estimates are checked to agree before the times are reported. Run with
`.venv/bin/python benchmarks/batch_filter.py`; the output is pasted into book/performance.md.
"""
from __future__ import annotations

import os
import platform
import time

import numpy as np

from kftrack.kalman import kalman_filter

RUNS, STEPS, DT, Q_DENSITY, SIGMA_Z = 1000, 1000, 1.0, 0.1, 5.0


def cv2d(dt: float, q: float):
    Fa = np.array([[1.0, dt], [0.0, 1.0]])
    Qa = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    H = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    return np.kron(np.eye(2), Fa), np.kron(np.eye(2), Qa), H


def main() -> None:
    rng = np.random.default_rng(2026)
    F, Q, H = cv2d(DT, Q_DENSITY)
    R = SIGMA_Z**2 * np.eye(2)
    x = np.zeros((RUNS, 4))
    zs = np.empty((STEPS, RUNS, 2))
    L = np.linalg.cholesky(Q)
    for k in range(STEPS):
        zs[k] = x @ H.T + SIGMA_Z * rng.standard_normal((RUNS, 2))
        x = x @ F.T + rng.standard_normal((RUNS, 4)) @ L.T
    x0, P0 = np.zeros(4), 100.0 * np.eye(4)

    best_batch = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        batch = kalman_filter(zs, x0, P0, F, Q, H, R)
        best_batch = min(best_batch, time.perf_counter() - t0)

    t0 = time.perf_counter()
    loop_x = np.empty_like(batch.x)
    for r in range(RUNS):
        loop_x[:, r] = kalman_filter(zs[:, r], x0, P0, F, Q, H, R).x
    t_loop = time.perf_counter() - t0

    assert np.allclose(loop_x, batch.x, rtol=1e-10, atol=1e-8), "batch and loop disagree"
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, NumPy {np.__version__}")
    print(f"{RUNS} runs x {STEPS} steps, 2-D constant velocity (n = 4, m = 2)")
    print("| path | time (s) | per run-step (us) |")
    print("|---|---|---|")
    print(f"| batch: one call, broadcast over runs | {best_batch:.2f} | {1e6 * best_batch / (RUNS * STEPS):.2f} |")
    print(f"| loop: one call per run | {t_loop:.2f} | {1e6 * t_loop / (RUNS * STEPS):.2f} |")
    print(f"speed-up: {t_loop / best_batch:.0f}x")


if __name__ == "__main__":
    main()
