"""Training-only reward shaping: hold still once in formation, do not touch another arm, and be precise.

For each agent row i of a step, on the observation the step ended in:

``r_i' = r_i - hold_penalty * [every incident edge of i within tolerance] * min(1, |dq_i| / SPEED_SCALE)
            - contact_penalty * [arm i has a contact point with another arm]
            + precision_bonus * [every incident edge of i within precision_band metres of its length]``

the first and last terms read from agent i's own observation (:func:`hold_penalty_factors`,
:func:`precision_factors`), the second from the env's ``contacts`` info (both arms of a contact pay). The
precision bonus pays for what the success band (1 cm by default) does not see: an edge held within 1 mm rather
than parked a few millimetres off. With ``hold_penalty <= 1`` an in-formation step still earns more
than any step outside it, so leaving the formation never pays. :func:`shaped_rewards` applies both to the
training env's K x N rewards; evaluation always uses the env's own reward. Why each term and the choice of
``SPEED_SCALE``, with the figures: the training docs (docs/training.md, "Why these defaults").
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

SPEED_SCALE = 0.05  # rad/s: joint speed (2-norm over the arm's joints) at which the hold penalty is full


def check_hold_penalty(hold_penalty: float) -> None:
    """``ValueError`` naming the field for a hold penalty outside [0, 1]."""
    if not 0 <= hold_penalty <= 1:
        raise ValueError(f"hold_penalty: expected a value in [0, 1], got {hold_penalty!r}")


def check_contact_penalty(contact_penalty: float) -> None:
    """``ValueError`` naming the field for a contact penalty that is not a finite value >= 0."""
    if not (np.isfinite(contact_penalty) and contact_penalty >= 0):
        raise ValueError(f"contact_penalty: expected a finite value >= 0, got {contact_penalty!r}")


def hold_penalty_factors(layout: Any, observations: np.ndarray) -> np.ndarray:
    """``[every real slot within tolerance] * min(1, |dq| / SPEED_SCALE)`` for a stack (k, size) of
    observations of one layout: (k,)."""
    ratios, real = layout.error_ratios(observations)  # (k, slots, w), (k, slots)
    inside = np.all((np.abs(ratios) <= 1.0) | ~real[..., None], axis=(1, 2))
    speeds = np.linalg.norm(layout.split(observations).dq, axis=1)
    return np.where(inside, np.minimum(1.0, speeds / SPEED_SCALE), 0.0)


def precision_factors(layout: Any, observations: np.ndarray, band: float) -> np.ndarray:
    """``[every real slot's edge length error <= band]`` (m) for a stack (k, size) of observations of one
    layout: (k,) of 0.0 or 1.0."""
    errors, _ = layout.length_errors(observations)  # (k, slots) m, 0 for padding
    return np.all(errors <= band, axis=1).astype(np.float64)


def shaped_rewards(rewards: np.ndarray, observations: np.ndarray, contacts: np.ndarray,
                   layout_rows: Sequence[tuple[Any, np.ndarray]], hold_penalty: float,
                   contact_penalty: float, precision_bonus: float = 0.0, precision_band: float = 1e-3) -> np.ndarray:
    """The rewards (K, N) with the penalties and the bonus (module docstring). ``observations`` (K * N, size): the raw
    observations each step ended in, copy-major (rows of a mixed team zero-padded: each layout reads its own
    entries); ``contacts`` (K, N): each arm's contact points with other
    arms; ``layout_rows``: (layout, the rows of that layout). A penalty or bonus of 0 leaves the rewards as they
    are."""
    if hold_penalty > 0:
        factors = np.empty(len(observations))
        for layout, rows in layout_rows:
            factors[rows] = hold_penalty_factors(layout, observations[rows, :layout.size])
        rewards = rewards - hold_penalty * factors.reshape(rewards.shape)
    if contact_penalty > 0:
        rewards = rewards - contact_penalty * (contacts > 0)
    if precision_bonus > 0:
        factors = np.empty(len(observations))
        for layout, rows in layout_rows:
            factors[rows] = precision_factors(layout, observations[rows, :layout.size], precision_band)
        rewards = rewards + precision_bonus * factors.reshape(rewards.shape)
    return rewards
