#!/usr/bin/env python3
"""GTSAM anchor for `kfmap optimize-graph` (install `gtsam numpy` in a venv outside the
repository): parking-garage.g2o with a tight prior on pose 0, Gauss-Newton, the error
before and after (GTSAM's error is half the chi2) and the time. With a second argument
(a g2o file written by kfmap), also GTSAM's error at those poses.
"""
import pathlib
import sys
import time

import gtsam
import numpy as np

DATA = pathlib.Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "g2o" / "parking-garage.g2o"


def graph_with_prior(path):
    graph, initial = gtsam.readG2o(str(path), True)
    prior = gtsam.noiseModel.Diagonal.Variances(np.full(6, 1e-6))
    graph.add(gtsam.PriorFactorPose3(0, initial.atPose3(0), prior))
    return graph, initial


def main():
    graph, initial = graph_with_prior(DATA)
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(1e-5)
    params.setMaxIterations(100)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        optimizer = gtsam.GaussNewtonOptimizer(graph, initial, params)
        result = optimizer.optimize()
        times.append(time.perf_counter() - t0)
    print(f"initial error {graph.error(initial):.6f}, final {graph.error(result):.6f}, "
          f"{optimizer.iterations()} iterations, median {np.median(times) * 1e3:.1f} ms")
    if len(sys.argv) > 1:
        _, ours = gtsam.readG2o(sys.argv[1], True)
        print(f"GTSAM error at {sys.argv[1]}: {graph.error(ours):.6f}")


if __name__ == "__main__":
    main()
