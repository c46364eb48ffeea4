"""Solvers and kernels on arrays and plain settings: OMP, K-SVD, dictionaries, the region and non-local solvers, the classical baselines."""
