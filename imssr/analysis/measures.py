"""The three per-state quantities of ``imssr analyze`` (paper, Section III, inequality finalbound).

* :func:`signal_of_states`: the left-hand side, ``rho(z', z)``, the agent's raw intrinsic signal.
* :func:`nuisance_distance`: term (ii), ``rho(h(x, n), h(x, n0))``, the distance between the
  encoder's latents of the same physics state rendered in a test scene and in ``training``.
* :func:`knn_distance` over :func:`state_coordinates`: a proxy for term (i), which needs the
  ideal encoder and cannot be measured: the distance to the k-th nearest other recorded state.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from imssr.analysis.adapter import batch_size, encoder_latents, intrinsic_signal
from imssr.errors import ImssrError


# -- (lhs) the intrinsic signal ---------------------------------------------------------------
def signal_of_states(agent, sample: dict[str, np.ndarray], padding: dict[str, np.ndarray]) -> np.ndarray:
    """:func:`intrinsic_signal` of every transition of ``sample`` in batches of the agent's RL batch
    size, the last one topped up from ``padding`` (more replay transitions), as the agent sees them."""
    size = batch_size(agent)
    n = len(sample["obs"])
    out = np.empty(n)
    for start in range(0, n, size):
        part = {k: v[start:start + size] for k, v in sample.items()}
        m = len(part["obs"])
        if m < size:
            part = {k: np.concatenate([v, padding[k][:size - m]]) for k, v in part.items()}
        out[start:start + m] = intrinsic_signal(agent, part)[:m].double().cpu().numpy()
    return out


# -- (ii) nuisance sensitivity ----------------------------------------------------------------------
def nuisance_distance(agent, clean: np.ndarray, shifted: np.ndarray) -> np.ndarray:
    """``||h(x, n) - h(x, n0)||`` per state: ``clean`` the stacks in ``training`` (n0), ``shifted``
    the same physics states in a test scene (n).  Zero where the pixels are equal."""
    if clean.shape != shifted.shape:
        raise ImssrError(f"stacks of shape {clean.shape} and {shifted.shape} cannot be compared")
    return np.linalg.norm(encoder_latents(agent, shifted) - encoder_latents(agent, clean), axis=1)


# -- (i) novelty --------------------------------------------------------------------------------
def state_coordinates(physics, states: np.ndarray) -> np.ndarray:
    """Physics states ``(M, nq + nv + na)`` as coordinates of the true state space: each hinge
    without a range (cartpole's pole, which may turn over and over) becomes ``(cos, sin)`` of its
    angle, so a full turn is the same state; every other position, velocity and activation is kept."""
    import mujoco

    m = physics.model
    nq = m.nq
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    wrap = [int(m.jnt_qposadr[j]) for j in range(m.njnt) if int(m.jnt_type[j]) == hinge and not bool(m.jnt_limited[j])]
    keep = [i for i in range(nq) if i not in wrap]
    angles = states[:, wrap]
    return np.concatenate([states[:, keep], np.cos(angles), np.sin(angles), states[:, nq:]], axis=1)


def standardise(coords: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``coords`` in units of the standard deviation of ``reference``'s finite rows, per coordinate
    (a coordinate that never varies is dropped: it tells no state from another)."""
    ref = reference[np.isfinite(reference).all(axis=1)]
    mean, std = ref.mean(axis=0), ref.std(axis=0)
    varies = std > 1e-12 * np.maximum(np.abs(mean), 1.0)
    return (coords[:, varies] - mean[varies]) / std[varies]


def knn_distance(query: np.ndarray, pool: np.ndarray, k: int, exclude: Optional[np.ndarray] = None) -> np.ndarray:
    """Distance from each ``query`` row to its ``k``-th nearest row of ``pool`` (NaN rows of ``pool`` are left out,
    and row ``exclude[i]`` for query ``i``: the state itself).  A state recorded ``k`` more times has novelty 0.
    NaN where the pool holds fewer than ``k`` others or the query row is not finite."""
    from scipy.spatial import cKDTree

    if k < 1:
        raise ImssrError(f"k must be >= 1, got {k}")
    query = np.asarray(query, dtype=np.float64)
    out = np.full(len(query), np.nan)
    rows = np.flatnonzero(np.isfinite(pool).all(axis=1))
    ok = np.isfinite(query).all(axis=1)
    if len(rows) == 0 or not ok.any():
        return out
    # One neighbour more than k: the excluded row may be among the nearest.
    dist, j = cKDTree(pool[rows]).query(query[ok], k=list(range(1, min(k + 1, len(rows)) + 1)))
    found = j < len(rows)  # missing neighbours come back as index len(rows), distance inf
    idx = np.where(found, rows[np.minimum(j, len(rows) - 1)], -1)
    ex = np.full(len(query), -1) if exclude is None else np.asarray(exclude)
    keep = found & (idx != ex[ok][:, None])
    hit = keep & (np.cumsum(keep, axis=1) == k)
    has = hit.any(axis=1)
    res = np.full(int(ok.sum()), np.nan)
    res[has] = dist[has, hit[has].argmax(axis=1)]
    out[ok] = res
    return out


def first_visit(query: np.ndarray, pool: np.ndarray, pool_step: np.ndarray, radius: float,
                own_step: np.ndarray) -> np.ndarray:
    """The earliest agent step at which a recorded state within ``radius`` of each query state
    (itself included, via ``own_step``) was stored; -1 where the steps are unknown."""
    known = (pool_step >= 0) & np.isfinite(pool).all(axis=1)
    out = np.asarray(own_step, dtype=np.int64).copy()
    pts, steps = pool[known], pool_step[known]
    for i, q in enumerate(query):
        near = np.sqrt(((pts - q) ** 2).sum(axis=1)) <= radius
        if near.any():
            first = int(steps[near].min())
            out[i] = first if out[i] < 0 else min(first, int(out[i]))
    return out
