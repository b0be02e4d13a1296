"""Sampled workspaces of arms: where an end-effector can be, and how far it reaches.

Used by the task (reaches, which bound the observations), by the validation (is the shape reachable?) and
by the scenario generators of the benchmarks.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ee_formation_env.kinematics import chain_model


@dataclass(frozen=True)
class Workspace:
    """Occupancy grid of an arm's reachable end-effector positions in its base frame (first ``dim`` axes)."""

    origin: np.ndarray  # (dim,) m, lower corner of cell 0
    cell: float  # m
    occupied: np.ndarray  # bool grid, dim axes
    reach: float  # m, largest distance of a sampled position from the base origin

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Which of the (k, dim) base-frame points fall in an occupied cell."""
        index = np.floor((points - self.origin) / self.cell).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(self.occupied.shape)), axis=1)
        result = np.zeros(len(points), dtype=bool)
        result[inside] = self.occupied[tuple(index[inside].T)]
        return result

    def cell_centres(self) -> np.ndarray:
        """(k, dim) base-frame centres of the occupied cells."""
        return (np.argwhere(self.occupied) + 0.5) * self.cell + self.origin


@functools.lru_cache(maxsize=32)
def workspace(urdf: str, ee_link: str, dim: int) -> Workspace:
    """Sampled workspace of an arm (seeded, so validation is deterministic), dilated by one cell.

    The dilation makes the test generous: a shape is reported out of reach only when it is clearly so.
    """
    model = chain_model(urdf, ee_link)
    rng = np.random.default_rng(0)
    count, cells_across_reach = (20_000, 40) if dim == 2 else (60_000, 14)
    points = model.forward_batch(model.sample_configurations(count, rng))[:, :dim]
    reach = float(np.max(np.linalg.norm(points, axis=1)))
    cell = max(reach, 1e-3) / cells_across_reach
    origin = points.min(axis=0) - 2 * cell
    index = np.floor((points - origin) / cell).astype(np.int64)
    grid = np.zeros(tuple(index.max(axis=0) + 3), dtype=bool)
    grid[tuple(index.T)] = True
    dilated = grid.copy()
    for axis in range(dim):
        dilated |= np.roll(grid, 1, axis=axis) | np.roll(grid, -1, axis=axis)
    return Workspace(origin=origin, cell=cell, occupied=dilated, reach=reach)
