"""Solvers: ICP, Levenberg-Marquardt factor graph, alignment (pure JAX)."""
