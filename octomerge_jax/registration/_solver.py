"""A small interface around the one third-party optimiser we use (jaxopt's L-BFGS).

jaxopt is no longer maintained and warns (``DeprecationWarning``) when imported. It is imported
lazily, only here, with exactly that warning silenced, so importing ``octomerge_jax`` never
triggers it and nothing else in the package depends on jaxopt's API. Everything the callers see
is ``minimize`` and ``MinimizeResult``: swapping the backend (optax's L-BFGS, optimistix's BFGS,
a hand-written Gauss-Newton) only touches this file.

``minimize`` runs the solver's ``init_state``/``update`` steps in our own ``lax.while_loop`` so
that it can (a) record the objective after every iteration in a static-size history, (b) stop
on a step-size criterion as well as on the gradient norm (our objectives are piecewise smooth:
trilinear interpolation has kinks at voxel centres, where the gradient norm need not vanish at
a minimum), and (c) run under ``jit`` and ``vmap`` with ``maxiter`` static and tolerances traced.
"""

from __future__ import annotations

import warnings
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["MinimizeResult", "minimize"]

_JAXOPT = None


def _jaxopt():
    """Import jaxopt once, silencing only its own "no longer maintained" deprecation notice."""
    global _JAXOPT
    if _JAXOPT is None:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="JAXopt is no longer maintained",
                                    category=DeprecationWarning)
            import jaxopt
        _JAXOPT = jaxopt
    return _JAXOPT


class MinimizeResult(NamedTuple):
    """Outcome of ``minimize`` (arrays; batched under ``vmap``).

    - ``x``: ``(n,)`` final parameters.
    - ``value``: ``()`` objective at ``x``.
    - ``history``: ``(maxiter + 1,)`` objective at ``x_0, x_1, ...``; NaN after the last iterate.
    - ``num_iterations``: ``()`` int32 solver iterations performed.
    - ``converged``: ``()`` bool, the gradient norm fell to ``tol`` or the last step was
      ``patience`` consecutive steps were shorter than ``xtol`` (not merely ``maxiter`` reached).
    - ``grad_norm``: ``()`` gradient norm at ``x``.
    """

    x: jax.Array
    value: jax.Array
    history: jax.Array
    num_iterations: jax.Array
    converged: jax.Array
    grad_norm: jax.Array


def minimize(fun: Callable, x0, *args, maxiter: int, tol=1e-4, xtol=1e-5,
             max_stepsize: float = 1.0, history_size: int = 10, patience: int = 3) -> MinimizeResult:
    """Minimise the scalar ``fun(x, *args)`` from ``x0 (n,)`` with L-BFGS and an Armijo
    backtracking line search that starts every iteration from ``max_stepsize`` (the natural
    quasi-Newton step). Measured on our alignment losses: jaxopt's default "increase"
    initialisation failed its first iterations; zoom and Hager-Zhang compiled 3-4x slower.

    ``maxiter``, ``history_size``, ``max_stepsize`` and ``patience`` are static; ``tol``
    (gradient norm) and ``xtol`` (Euclidean length of a step, in the units of ``x``) may be
    traced. Stops when the gradient norm is ``<= tol``, ``patience`` consecutive steps are
    ``<= xtol`` (a failed line search restarts the L-BFGS memory and can give one null step
    that is not yet convergence), the objective becomes non-finite, or after ``maxiter``
    iterations. Pure: jittable and vmappable.
    """
    jaxopt = _jaxopt()
    with warnings.catch_warnings():
        # jaxopt marks ``condition`` deprecated but still needs it: its default for the
        # backtracking search is strong Wolfe, which fails on piecewise-smooth losses.
        warnings.filterwarnings("ignore", message="Argument condition is deprecated",
                                category=DeprecationWarning)
        solver = jaxopt.LBFGS(fun=fun, maxiter=int(maxiter), tol=0.0,
                              max_stepsize=float(max_stepsize), history_size=int(history_size),
                              implicit_diff=False, jit=True, linesearch="backtracking",
                              linesearch_init="max", condition="armijo",
                              stop_if_linesearch_fails=False)
    x0 = jnp.asarray(x0)
    state0 = solver.init_state(x0, *args)
    hist0 = jnp.full((int(maxiter) + 1,), jnp.nan, state0.value.dtype).at[0].set(state0.value)
    tol = jnp.asarray(tol, x0.dtype)
    xtol = jnp.asarray(xtol, x0.dtype)

    def cond(carry):
        it, done = carry[3], carry[4]
        return (~done) & (it < maxiter)

    def body(carry):
        x, state, hist, it, _, stalls, _ = carry
        x_new, state_new = solver.update(x, state, *args)
        ok = jnp.isfinite(state_new.value) & jnp.all(jnp.isfinite(x_new))
        step = jnp.where(ok, jnp.linalg.norm(x_new - x), jnp.zeros((), x0.dtype))
        x_new = jnp.where(ok, x_new, x)
        state_new = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), state_new, state)
        hist = hist.at[it + 1].set(jnp.where(ok, state_new.value, jnp.nan))
        stalls = jnp.where(step <= xtol, stalls + 1, 0)
        done = (~ok) | (state_new.error <= tol) | (stalls >= patience)
        return x_new, state_new, hist, it + 1, done, stalls, ~ok

    init = (x0, state0, hist0, jnp.int32(0), state0.error <= tol, jnp.int32(0), jnp.bool_(False))
    x, state, hist, it, _, stalls, bad = jax.lax.while_loop(cond, body, init)
    value = fun(x, *args)
    # Converged: small gradient or stalled steps, never by running out of iterations while
    # still moving, and never after a non-finite objective.
    converged = (jnp.isfinite(value) & ~bad) & ((state.error <= tol) | (stalls >= patience))
    return MinimizeResult(x=x, value=value, history=hist, num_iterations=it,
                          converged=converged, grad_norm=state.error)
