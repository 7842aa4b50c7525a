"""The Sim(3) pose graph over chunk transforms: overlap constraints plus loop closures.

Overlaps give ``G_{k-1}^{-1} G_k ≈ A_k``, kept loops ``G_other^{-1} G_chunk ≈ T``; solved on the
chart ``(ω, t, log s)`` (:mod:`cm3d.solvers.sim3_pose_graph`), so a loop corrects scale drift. A loop
inconsistent with the chain (χ² test) is left out.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from cm3d.long_video.layout import StitchError
from cm3d.ops import robust


@dataclasses.dataclass(frozen=True)
class PoseGraphConfig:
    """The Sim(3) pose graph over chunk transforms (:func:`sim3_pose_graph`).

    sigma_rot (rad), sigma_trans (chunk 0's units), sigma_scale (log scale): noise of an overlap
    constraint; loop_factor: loop sigmas are this many times larger (docs/long_video.md: why 20);
    max_steps: LM steps; loop_quantile: keep a loop when ``|r|² <= χ²_q(7)`` (1 keeps every loop).
    """

    sigma_rot: float = 0.01
    sigma_trans: float = 0.01
    sigma_scale: float = 0.01
    loop_factor: float = 20.0
    max_steps: int = 100
    loop_quantile: float = 0.99

    def __post_init__(self):
        for name in ("sigma_rot", "sigma_trans", "sigma_scale", "loop_factor"):
            if not getattr(self, name) > 0:
                raise ValueError(f"PoseGraphConfig.{name}: must be > 0, got {getattr(self, name)}")
        if self.max_steps < 1:
            raise ValueError(f"PoseGraphConfig.max_steps: must be >= 1, got {self.max_steps}")

    @property
    def sigmas(self) -> np.ndarray:
        """(7,) sigmas of an overlap constraint in the chart ``(ω, t, log s)``."""
        return np.array([self.sigma_rot] * 3 + [self.sigma_trans] * 3 + [self.sigma_scale])


@dataclasses.dataclass(frozen=True)
class LoopClosure:
    """A memory recall across chunks: a window of ``chunk`` (its frames) recalled a map that a window
    of ``other`` (``other_frames``) created; ``transform`` (4, 4) Sim(3) ``chunk``'s frame -> ``other``'s;
    inliers / rmse: ICP facts; ``measured``: the memory's own transform between refined frames when
    ``transform`` was re-expressed between prior frames, else None."""

    chunk: int
    other: int
    frames: tuple[int, int]
    transform: np.ndarray
    inliers: int
    rmse: float
    other_frames: tuple[int, int] | None = None
    measured: np.ndarray | None = None


def sim3_pose_graph(G0, A, loops=(), cfg: PoseGraphConfig = PoseGraphConfig()):
    """Refine the chunk transforms ``G_k`` (chunk k -> common frame, Sim(3), ``G_0 = I``).

    G0 (K, 4, 4) initial transforms; A (K, 4, 4), A[k] chunk k -> k-1; loops: :class:`LoopClosure`
    list. Without a kept loop the chain of A is returned. Returns (G (K, 4, 4) float64, facts dict).
    """
    from cm3d.solvers import sim3_pose_graph as spg

    G0 = np.asarray(G0, np.float64)
    K = G0.shape[0]
    if K < 2:
        return G0, {"constraints": 0, "loops": 0, "loops_kept": 0}
    base = cfg.sigmas
    ia, ib = list(range(K - 1)), list(range(1, K))
    meas, sig = [np.asarray(A[k], np.float64) for k in range(1, K)], [base] * (K - 1)
    limit = float(robust.chi2_quantile(cfg.loop_quantile, 7)) if cfg.loop_quantile < 1 else np.inf
    chain = [np.eye(4)]
    for k in range(1, K):
        chain.append(chain[-1] @ np.asarray(A[k], np.float64))
    chain = np.stack(chain)
    zero = jnp.zeros((K - 1, 7))
    discrepancy, kept = [], 0
    for lc in loops:
        if not (0 <= lc.other < K and 0 <= lc.chunk < K) or lc.other == lc.chunk:
            raise StitchError(f"loops: chunk {lc.chunk} -> {lc.other} is not a pair of distinct chunks of {K}")
        loop_sigma = base * cfg.loop_factor
        chain_sigma = np.sqrt(base ** 2 * abs(lc.chunk - lc.other) + loop_sigma ** 2)
        r = spg.residuals(zero, jnp.asarray(chain), jnp.asarray([lc.other]), jnp.asarray([lc.chunk]),
                          jnp.asarray(np.asarray(lc.transform, np.float64)[None]), jnp.asarray(chain_sigma[None]))
        d2 = float(jnp.sum(r * r))
        discrepancy.append(d2)
        if d2 <= limit:
            kept += 1
            ia.append(lc.other), ib.append(lc.chunk), meas.append(np.asarray(lc.transform, np.float64))
            sig.append(loop_sigma)
    facts = {"constraints": len(ia), "loops": len(loops), "loops_kept": kept, "loop_limit": limit,
             "loop_discrepancy_max": max(discrepancy) if discrepancy else 0.0,
             "loop_discrepancy": discrepancy, "loop_kept": [d2 <= limit for d2 in discrepancy]}
    if kept == 0:  # a chain (a tree) of constraints: the chained transforms satisfy every one exactly
        return chain, {**facts, "cost_initial": 0.0, "cost": 0.0, "steps": 0}
    sol = spg.solve(jnp.asarray(G0), jnp.asarray(ia), jnp.asarray(ib), jnp.asarray(np.stack(meas)),
                    jnp.asarray(np.stack(sig)), max_steps=cfg.max_steps)
    return np.asarray(sol.transforms, np.float64), {**facts, "cost_initial": float(sol.cost_initial),
                                                    "cost": float(sol.cost), "steps": int(sol.steps)}
