"""A pose graph over SE(3): many maps' frames made to agree with pairwise measurements.

Node k is the transform ``T_0_k`` of map k's frame into map 0's (node 0 fixed: the gauge). Edge
e measures ``Z_e = T_i_j`` (map j's frame into map i's) with information ``Omega_e`` (6 x 6, in
the tangent space of the right perturbation ``Z exp(delta)``, ``delta = (v [m], omega [rad])``,
``se3.se3_exp``'s order). The residual of an edge is ``r = log(Z^-1 T_0_i^-1 T_0_j)`` and the
cost ``sum_e rho(r_e^T Omega_e r_e)`` with a robust kernel ``rho`` (Cauchy, or Geman-McClure)
on measurement edges and the plain square on priors (user guesses). The solver is
Levenberg-Marquardt on the manifold (``T <- T exp(dx)``) with iteratively reweighted normal
equations, jitted over padded arrays: one compiled program per (node, edge) capacity bucket.

On the host around it (``solve_robust``): a cycle-consistency check over every triangle of
the graph (a measurement that closes no consistent triangle and at least one inconsistent one
is rejected), a max-confidence spanning tree for the initial poses, then solves that drop any
measurement whose residual after the solve exceeds ``max_chi2`` until none does; measurements
the cycle check rejected that agree with that solution are taken back and the graph solved
again (once). When the measurements in use form just the spanning tree (a chain of pairs, no
loop to close), the tree's chained float64 poses are the optimum and are returned as they are.
The marginal covariance of every pose is the inverse of the final Gauss-Newton Hessian.
References: Grisetti et al., "A tutorial on graph-based SLAM" (2010); Yang et al., "Graduated
non-convexity for robust spatial perception" (2020) for the kernels; map_merge_3d and
Kimera-Multi for pairwise measurements plus outlier rejection
(``docs/design.md``, "Pose graph over pairwise registrations").
"""

from __future__ import annotations

import dataclasses
import itertools
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import se3
from .._ops import bucket_capacity

__all__ = ["GraphSolution", "PoseGraph", "RobustResult", "cycle_chi2", "edge_residuals", "make_graph",
           "solve_pose_graph", "solve_robust", "spanning_tree_poses", "triangles"]

KERNELS = ("cauchy", "geman_mcclure", "none")
CHI2_6DOF_999 = 22.46  # chi-square, 6 degrees of freedom, 99.9 % quantile


class PoseGraph(NamedTuple):
    """A padded pose graph (a pytree of arrays; ``m`` edges, capacity ``M``)."""

    i: jax.Array  # (M,) int32: edge's first node (the measurement's target frame)
    j: jax.Array  # (M,) int32: edge's second node (source frame)
    T_i_j: jax.Array  # (M, 4, 4) float32: measurement, map j's frame into map i's [m]
    information: jax.Array  # (M, 6, 6) float32: Omega, (v [1/m^2], omega [1/rad^2]) blocks
    active: jax.Array  # (M,) bool: used in the solve (false: padding or rejected)
    robust: jax.Array  # (M,) bool: the robust kernel applies (false: priors)


class GraphSolution(NamedTuple):
    """``solve_pose_graph``'s result (device arrays)."""

    T_0_k: jax.Array  # (N, 4, 4) float32: poses [m]
    chi2: jax.Array  # (M,) float32: r^T Omega r per edge at the solution (0 for inactive)
    weight: jax.Array  # (M,) float32: the robust kernel's weight at the solution
    covariance: jax.Array  # (N, 6, 6) float32: marginal covariance of each free pose (0 if fixed)
    cost: jax.Array  # () float32: robust cost at the solution
    num_iterations: jax.Array  # () int32
    converged: jax.Array  # () bool: the step fell below the tolerance


def make_graph(i, j, T_i_j, information, robust=None, capacity: int | None = None) -> PoseGraph:
    """A ``PoseGraph`` padded to ``capacity`` edges (default: the power-of-two bucket of ``m``)
    from host arrays ``i, j (m,)``, ``T_i_j (m, 4, 4)``, ``information (m, 6, 6)`` and
    ``robust (m,)`` (default all true). Raises ``ValueError`` for mismatched lengths or a
    self-loop."""
    i, j = np.asarray(i, np.int32).reshape(-1), np.asarray(j, np.int32).reshape(-1)
    m = i.shape[0]
    T = np.asarray(T_i_j, np.float32).reshape(m, 4, 4)
    info = np.asarray(information, np.float32).reshape(m, 6, 6)
    rob = np.ones(m, bool) if robust is None else np.asarray(robust, bool).reshape(m)
    if j.shape[0] != m:
        raise ValueError(f"i has {m} edges, j has {j.shape[0]}")
    if np.any(i == j):
        raise ValueError(f"edge {int(np.argmax(i == j))} joins node {int(i[i == j][0])} to itself")
    cap = bucket_capacity(m, 16) if capacity is None else int(capacity)
    pad = cap - m
    eye = np.broadcast_to(np.eye(4, dtype=np.float32), (pad, 4, 4))
    return PoseGraph(i=jnp.asarray(np.concatenate([i, np.zeros(pad, np.int32)])),
                     j=jnp.asarray(np.concatenate([j, np.ones(pad, np.int32)])),
                     T_i_j=jnp.asarray(np.concatenate([T, eye])),
                     information=jnp.asarray(np.concatenate([info, np.zeros((pad, 6, 6), np.float32)])),
                     active=jnp.asarray(np.concatenate([np.ones(m, bool), np.zeros(pad, bool)])),
                     robust=jnp.asarray(np.concatenate([rob, np.zeros(pad, bool)])))


def edge_residuals(T_0_k, graph: PoseGraph):
    """``(M, 6)`` residuals ``log(Z^-1 T_0_i^-1 T_0_j)`` of every edge at poses ``T_0_k (N, 4, 4)``."""
    return se3.se3_log(se3.inverse(graph.T_i_j) @ se3.inverse(T_0_k[graph.i]) @ T_0_k[graph.j])


def _edge_jacobians(T_0_k, graph: PoseGraph, r):
    """``(J_i, J_j)`` ``(M, 6, 6)``: the residual's derivatives under ``T_0_i exp(d_i)``,
    ``T_0_j exp(d_j)``: ``J_j = Jr^-1(r)``, ``J_i = -Jr^-1(r) Ad(T_0_j^-1 T_0_i)``."""
    Jr = se3.right_jacobian_inverse(r)
    return -Jr @ se3.adjoint(se3.inverse(T_0_k[graph.j]) @ T_0_k[graph.i]), Jr


def _kernel(chi2, scale2, kernel: str):
    """``(rho, weight = rho')`` of the robust kernel at ``chi2`` with scale ``scale2``."""
    u = chi2 / scale2
    if kernel == "cauchy":
        return scale2 * jnp.log1p(u), 1.0 / (1.0 + u)
    if kernel == "geman_mcclure":
        return scale2 * u / (1.0 + u), 1.0 / (1.0 + u) ** 2
    return chi2, jnp.ones_like(chi2)


def _costs(T, graph: PoseGraph, scale2, kernel: str):
    r = edge_residuals(T, graph)
    chi2 = jnp.einsum("mi,mij,mj->m", r, graph.information, r)
    rho, w = _kernel(chi2, scale2, kernel)
    rho = jnp.where(graph.robust, rho, chi2)
    w = jnp.where(graph.robust, w, 1.0)
    return jnp.where(graph.active, rho, 0.0), jnp.where(graph.active, w, 0.0), jnp.where(graph.active, chi2, 0.0), r


def _normal_equations(T, graph: PoseGraph, free, scale2, kernel: str):
    """``(H (6N, 6N), g (6N,), cost)`` of the reweighted Gauss-Newton step; fixed nodes get
    identity rows."""
    n = T.shape[0]
    rho, w, _, r = _costs(T, graph, scale2, kernel)
    J_i, J_j = _edge_jacobians(T, graph, r)  # (M, 6, 6) each
    J = jnp.concatenate([J_i, J_j], -1)  # (M, 6, 12)
    WO = w[:, None, None] * graph.information
    He = jnp.einsum("mai,mab,mbj->mij", J, WO, J)  # (M, 12, 12)
    ge = jnp.einsum("mai,mab,mb->mi", J, WO, r)  # (M, 12)
    idx = jnp.concatenate([graph.i[:, None] * 6 + jnp.arange(6), graph.j[:, None] * 6 + jnp.arange(6)], -1)
    H = jnp.zeros((6 * n, 6 * n), T.dtype).at[idx[:, :, None], idx[:, None, :]].add(He)
    g = jnp.zeros(6 * n, T.dtype).at[idx].add(ge)
    f = jnp.repeat(free, 6)
    H = jnp.where(f[:, None] & f[None, :], H, 0.0) + jnp.diag(jnp.where(f, 0.0, 1.0))
    return H, jnp.where(f, g, 0.0), jnp.sum(rho)


class _LMState(NamedTuple):
    T: jax.Array  # (N, 4, 4) poses
    cost: jax.Array  # () robust cost at T
    lam: jax.Array  # () damping
    step: jax.Array  # () last step's largest |dx|
    it: jax.Array  # () int32 iterations done


@partial(jax.jit, static_argnames=("max_iterations", "kernel"))
def solve_pose_graph(T_init, graph: PoseGraph, free, kernel_scale=3.0, tolerance=1e-6, *,
                     max_iterations: int = 50, kernel: str = "cauchy") -> GraphSolution:
    """Levenberg-Marquardt over SE(3) from ``T_init (N, 4, 4)`` (float32) on ``graph``.

    Args:
      free: ``(N,)`` bool, poses that move (node 0 and unplaced or padding nodes: false).
      kernel_scale: the robust kernel's scale in units of sqrt(chi2) (traced).
      tolerance: stop when the largest step component falls below it [m or rad] (traced).
      max_iterations: static bound on LM iterations.
      kernel: ``"cauchy"``, ``"geman_mcclure"`` or ``"none"`` (static).

    Returns a ``GraphSolution``; its covariance is the inverse of the (reweighted) Gauss-Newton
    Hessian at the solution, free-node blocks only.
    """
    T_init = jnp.asarray(T_init, jnp.float32)
    scale2 = jnp.asarray(kernel_scale, jnp.float32) ** 2

    def cost_at(T):
        return jnp.sum(_costs(T, graph, scale2, kernel)[0])

    def cond(s: _LMState):
        return (s.it < max_iterations) & (s.step > tolerance)

    def body(s: _LMState):
        H, g, _ = _normal_equations(s.T, graph, free, scale2, kernel)
        D = jnp.diag(jnp.maximum(jnp.diag(H), 1e-6))
        dx = jnp.linalg.solve(H + s.lam * D, -g).reshape(-1, 6)
        dx = jnp.where(free[:, None] & jnp.all(jnp.isfinite(dx)), dx, 0.0)
        T_new = s.T @ se3.se3_exp(dx)
        c_new = cost_at(T_new)
        better = c_new <= s.cost
        return _LMState(T=jnp.where(better, T_new, s.T), cost=jnp.where(better, c_new, s.cost),
                        lam=jnp.where(better, s.lam / 3.0, s.lam * 4.0),
                        step=jnp.where(better | (s.lam < 1e8), jnp.max(jnp.abs(dx)), 0.0), it=s.it + 1)

    s = jax.lax.while_loop(cond, body, _LMState(T_init, cost_at(T_init), jnp.float32(1e-3), jnp.float32(jnp.inf),
                                                jnp.int32(0)))
    H, _, _ = _normal_equations(s.T, graph, free, scale2, kernel)
    cov = jnp.linalg.inv(H)
    n = s.T.shape[0]
    blocks = cov.reshape(n, 6, n, 6)[jnp.arange(n), :, jnp.arange(n), :]
    blocks = jnp.where(free[:, None, None], blocks, 0.0)
    rho, w, chi2, _ = _costs(s.T, graph, scale2, kernel)
    return GraphSolution(T_0_k=s.T, chi2=chi2, weight=w, covariance=blocks, cost=jnp.sum(rho),
                         num_iterations=s.it, converged=s.step <= tolerance)


# ----------------------------------------------------------------------------- cycle checks


def triangles(i, j, usable) -> tuple[np.ndarray, np.ndarray]:
    """Host plan of the cycle check: every triangle of the graph over the ``usable`` edges
    (``i, j, usable (m,)``; one edge per node pair, the first). Returns ``(edges (t, 3) int,
    flip (t, 3) bool)``: the triangle ``a < b < c`` as edges ``a->b, b->c, c->a``, each flipped
    (inverted) where the stored edge runs the other way."""
    pair = {}
    for e, (a, b, u) in enumerate(zip(np.asarray(i).tolist(), np.asarray(j).tolist(), np.asarray(usable).tolist())):
        if u:
            pair.setdefault((min(a, b), max(a, b)), e)
    nodes = sorted({n for p in pair for n in p})
    adj = {n: set() for n in nodes}
    for a, b in pair:
        adj[a].add(b)
        adj[b].add(a)
    edges, flip = [], []
    for a in nodes:
        for b, c in itertools.combinations(sorted(x for x in adj[a] if x > a), 2):
            if c not in adj[b]:
                continue
            tri = [(a, b), (b, c), (c, a)]
            es = [pair[(min(p, q), max(p, q))] for p, q in tri]
            edges.append(es)
            flip.append([int(np.asarray(i)[e]) != p for e, (p, q) in zip(es, tri)])
    return np.asarray(edges, np.int64).reshape(-1, 3), np.asarray(flip, bool).reshape(-1, 3)


def cycle_chi2(T_i_j, covariance, flip) -> np.ndarray:
    """Squared Mahalanobis norm ``(t,)`` of each triangle's loop ``C = P_1 P_2 P_3`` against the
    identity (host, float64): ``T_i_j (t, 3, 4, 4)`` and ``covariance (t, 3, 6, 6)`` of its three
    measurements (right perturbation), ``flip (t, 3)`` where a measurement is used inverted
    (``P = Z^-1``). The loop's covariance is propagated to ``r = log C`` through the adjoints
    ``Jr^-1(r) Ad(P_{k+1} P_3)^-1`` (times ``-Ad(Z_k)`` for a flipped one), so rotations between
    the frames are accounted for."""
    Z = np.asarray(T_i_j, np.float64)
    S = np.asarray(covariance, np.float64)
    flip = np.asarray(flip, bool)
    P = np.where(flip[..., None, None], np.linalg.inv(Z), Z)
    r = se3.se3_log(P[:, 0] @ P[:, 1] @ P[:, 2], xp=np)
    Jr = se3.right_jacobian_inverse(r, xp=np)
    after = [P[:, 1] @ P[:, 2], P[:, 2], np.broadcast_to(np.eye(4), P[:, 2].shape)]
    C = np.zeros((len(Z), 6, 6))
    for k in range(3):
        G = se3.adjoint(np.linalg.inv(after[k]), xp=np)
        G = np.where(flip[:, k, None, None], -G @ se3.adjoint(Z[:, k], xp=np), G)
        J = Jr @ G
        C += J @ S[:, k] @ np.swapaxes(J, -1, -2)
    C += 1e-12 * np.eye(6)
    return np.einsum("ti,ti->t", r, np.linalg.solve(C, r[..., None])[..., 0])


def spanning_tree_poses(n: int, i, j, T_i_j, score, usable) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Initial poses by chaining measurements along a maximum-``score`` spanning tree from node
    0 (Prim; host, float64). Returns ``(T_0_k (n, 4, 4), placed (n,) bool, tree edge indices)``;
    nodes not reached by ``usable`` edges keep the identity and ``placed = False``."""
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    placed = np.zeros(n, bool)
    placed[0] = True
    tree: list[int] = []
    i, j = np.asarray(i), np.asarray(j)
    Z = np.asarray(T_i_j, np.float64)
    while True:
        cand = [e for e in range(len(i)) if usable[e] and placed[i[e]] != placed[j[e]]]
        if not cand:
            return T, placed, tree
        e = max(cand, key=lambda e: (score[e], -e))
        if placed[i[e]]:
            T[j[e]] = T[i[e]] @ Z[e]
            placed[j[e]] = True
        else:
            T[i[e]] = T[j[e]] @ np.linalg.inv(Z[e])
            placed[i[e]] = True
        tree.append(e)


# ----------------------------------------------------------------------------- the robust procedure


@dataclasses.dataclass(frozen=True)
class RobustResult:
    """``solve_robust``'s result (host values).

    - ``T_0_k``: ``(n, 4, 4)`` float64 poses (identity for unplaced nodes).
    - ``placed``: ``(n,)`` bool, connected to node 0 by kept measurements.
    - ``covariance``: ``(n, 6, 6)`` float64 marginal covariance (v [m^2], omega [rad^2]);
      zeros for node 0, NaN for unplaced nodes.
    - ``kept``: ``(m,)`` bool; ``why``: per edge ``""`` (kept), ``"cycle"`` (closes only
      inconsistent triangles), ``"residual"`` (``chi2`` above ``max_chi2`` after a solve) or
      ``"unused"`` (given as not usable).
    - ``chi2``: ``(m,)`` float64 ``r^T Omega r`` at the final poses (for every edge, kept or not).
    - ``residual``: ``(m, 6)`` float64 residual ``log(Z^-1 T_0_i^-1 T_0_j)`` at the final poses.
    - ``cycles``: ``(t, 3)`` edge indices of the triangles checked; ``cycle_chi2``: ``(t,)``.
    - ``tree``: edge indices of the initial spanning tree of the final solve.
    - ``num_iterations``, ``rounds`` (solves), ``cost``, ``converged``.
    """

    T_0_k: np.ndarray
    placed: np.ndarray
    covariance: np.ndarray
    kept: np.ndarray
    why: tuple[str, ...]
    chi2: np.ndarray
    residual: np.ndarray
    cycles: np.ndarray
    cycle_chi2: np.ndarray
    tree: tuple[int, ...]
    num_iterations: int
    rounds: int
    cost: float
    converged: bool


def solve_robust(n: int, i, j, T_i_j, information, *, score=None, usable=None, prior=None,
                 kernel: str = "cauchy", kernel_scale: float = 3.0, max_chi2: float = CHI2_6DOF_999,
                 cycle_max_chi2: float = CHI2_6DOF_999, max_iterations: int = 50, max_rounds: int = 5) -> RobustResult:
    """The robust pose-graph solve of ``n`` maps (see the module docstring).

    Args:
      i, j, T_i_j, information: ``m`` measurements (``(m,)``, ``(m,)``, ``(m, 4, 4)`` [m],
        ``(m, 6, 6)``), host arrays.
      score: ``(m,)`` preference for the spanning tree (e.g. registration confidence; default 1).
      usable: ``(m,)`` bool, edges that may be used at all (default all).
      prior: ``(m,)`` bool, edges that are user guesses: plain squared cost, no cycle vote, never
        rejected, and they do not make a node placed.
      kernel, kernel_scale, max_iterations: ``solve_pose_graph``'s.
      max_chi2, cycle_max_chi2: rejection thresholds on an edge's / a triangle's chi2.
      max_rounds: solves at most (each drops the edge with the largest chi2 above ``max_chi2``).

    Returns a ``RobustResult``. Raises ``ValueError`` for ``n < 1`` or an unknown kernel.
    """
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if kernel not in KERNELS:
        raise ValueError(f"kernel: expected one of {KERNELS}, got {kernel!r}")
    i, j = np.asarray(i, np.int64).reshape(-1), np.asarray(j, np.int64).reshape(-1)
    m = len(i)
    Z = np.asarray(T_i_j, np.float64).reshape(m, 4, 4)
    info = np.asarray(information, np.float64).reshape(m, 6, 6)
    score = np.ones(m) if score is None else np.asarray(score, np.float64)
    usable = np.ones(m, bool) if usable is None else np.asarray(usable, bool).copy()
    prior = np.zeros(m, bool) if prior is None else np.asarray(prior, bool)
    why = ["" if u else "unused" for u in usable]
    meas = usable & ~prior
    # cycle check over every triangle of measurements
    cyc, flip = triangles(i, j, meas)
    cyc_chi2 = np.zeros(len(cyc))
    if len(cyc):
        cov = np.linalg.pinv(info)
        cyc_chi2 = cycle_chi2(Z[cyc], cov[cyc], flip)
        good, bad = np.zeros(m, int), np.zeros(m, int)
        ok = cyc_chi2 <= cycle_max_chi2
        np.add.at(good, cyc[ok].ravel(), 1)
        np.add.at(bad, cyc[~ok].ravel(), 1)
        for e in np.flatnonzero(meas & (bad > 0) & (good == 0)):
            why[e], meas[e] = "cycle", False
    n_cap = bucket_capacity(n, 8)
    rounds, sol, readmitted = 0, None, False
    while True:
        rounds += 1
        kept = meas | (prior & usable)
        T0, placed, tree = spanning_tree_poses(n, i, j, Z, score, meas)
        T0 = np.concatenate([T0, np.broadcast_to(np.eye(4), (n_cap - n, 4, 4))])
        free = np.zeros(n_cap, bool)
        free[:n] = placed
        free[0] = False
        active = kept & placed[i] & placed[j]  # a prior to an unplaced map would pull towards nothing
        graph = make_graph(i, j, Z, info * active[:, None, None], robust=~prior)
        graph = graph._replace(active=graph.active & jnp.asarray(np.pad(active, (0, graph.i.shape[0] - m))))
        sol = solve_pose_graph(T0.astype(np.float32), graph, jnp.asarray(free), kernel_scale,
                               max_iterations=max_iterations, kernel=kernel)
        chi2_all = _host_chi2(np.asarray(sol.T_0_k, np.float64)[:n], i, j, Z, info)[0]
        worst = np.flatnonzero(meas & (chi2_all > max_chi2) & placed[i] & placed[j])
        if rounds >= max_rounds:
            break
        if len(worst) == 0:
            # a triangle with one wrong edge condemns its other edges too when they close no other
            # triangle: those that agree with the solution of the rest are taken back, once
            back = np.array([w == "cycle" for w in why]) & placed[i] & placed[j] & (chi2_all <= max_chi2)
            if readmitted or not back.any():
                break
            readmitted = True
            meas |= back
            why = ["" if b else w for b, w in zip(back, why)]
            continue
        e = worst[np.argmax(chi2_all[worst])]  # one at a time: the worst may have pulled the others
        why[e], meas[e] = "residual", False
    if sorted(np.flatnonzero(active).tolist()) == sorted(tree):
        # the edges in use form the spanning tree: its chained float64 poses meet every one of
        # them exactly (the least-squares optimum), which the float32 solve only approximates
        T = T0[:n].copy()
    else:
        T = np.asarray(sol.T_0_k, np.float64)[:n]
    T = np.stack([se3.project_to_rigid(t) for t in T])
    T[~placed] = np.eye(4)
    cov = np.asarray(sol.covariance, np.float64)[:n]
    cov[~placed] = np.nan
    chi2, res = _host_chi2(T, i, j, Z, info)
    return RobustResult(T_0_k=T, placed=placed, covariance=cov, kept=meas | (prior & usable), why=tuple(why),
                        chi2=chi2, residual=res, cycles=cyc,
                        cycle_chi2=cyc_chi2, tree=tuple(int(e) for e in tree),
                        num_iterations=int(sol.num_iterations), rounds=rounds, cost=float(sol.cost),
                        converged=bool(sol.converged))


def _host_chi2(T, i, j, Z, info):
    """``(chi2 (m,), r (m, 6))`` of every edge at poses ``T (n, 4, 4)``, float64 on the host."""
    r = np.asarray(se3.se3_log(np.linalg.inv(Z) @ np.linalg.inv(T[i]) @ T[j], xp=np), np.float64)
    return np.einsum("mi,mij,mj->m", r, info, r), r
