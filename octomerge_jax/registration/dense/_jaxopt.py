"""The dense alignment's second minimiser backend: jaxopt's ``LBFGS`` behind ``minimize``'s
interface (``solver="jaxopt"`` in ``solve_alignment`` / ``align_dense``).

jaxopt is imported on first use: its import takes about a second and emits a deprecation
notice ("no longer maintained"), which only this backend's users should pay for; that one
notice is silenced here.
"""

from __future__ import annotations

import functools
import warnings
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from ._lbfgs import MinimizeResult

__all__ = ["minimize_jaxopt"]


class _Carry(NamedTuple):
    """Loop state of ``minimize_jaxopt``."""

    x: jax.Array       # (n,) current iterate
    state: Any         # jaxopt's LbfgsState at x
    hist: jax.Array    # (maxiter + 1,) objective after every iteration
    it: jax.Array      # () int32 iterations
    done: jax.Array    # () bool
    stalls: jax.Array  # () int32 consecutive steps shorter than xtol
    bad: jax.Array     # () bool, the objective became non-finite


@functools.cache
def _jaxopt():
    """Import jaxopt once, silencing only its own "no longer maintained" deprecation notice."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="JAXopt is no longer maintained",
                                category=DeprecationWarning)
        import jaxopt  # an optional backend: imported on use (see the module docstring)
    return jaxopt


def _lbfgs(fun: Callable, maxiter: int, max_stepsize: float, history_size: int):
    """jaxopt's ``LBFGS`` with a backtracking Armijo search started at ``max_stepsize``."""
    jaxopt = _jaxopt()
    with warnings.catch_warnings():
        # jaxopt marks ``condition`` deprecated but still needs it: its default for the
        # backtracking search is strong Wolfe, which fails on piecewise-smooth losses.
        warnings.filterwarnings("ignore", message="Argument condition is deprecated",
                                category=DeprecationWarning)
        return jaxopt.LBFGS(fun=fun, maxiter=int(maxiter), tol=0.0, max_stepsize=float(max_stepsize),
                            history_size=int(history_size), implicit_diff=False, jit=True,
                            linesearch="backtracking", linesearch_init="max", condition="armijo",
                            stop_if_linesearch_fails=False)


def minimize_jaxopt(fun: Callable, x0, *args, maxiter: int, tol=1e-4, xtol=1e-5,
                    max_stepsize: float = 1.0, history_size: int = 10, patience: int = 3,
                    has_aux: bool = False) -> MinimizeResult:
    """Minimise the scalar ``fun(x, *args)`` from ``x0 (n,)`` with jaxopt's L-BFGS (Nocedal &
    Wright Alg. 7.5) and an Armijo backtracking line search that starts every iteration from
    ``max_stepsize`` (the natural quasi-Newton step).

    Args:
      fun: scalar objective ``fun(x, *args)``, differentiable in ``x``.
      x0: ``(n,)`` start.
      maxiter, history_size, max_stepsize, patience: static.
      tol: gradient-norm tolerance (may be traced).
      xtol: Euclidean step length, units of ``x``, below which a step counts as stalled (may
        be traced).
      has_aux: static; ``fun`` returns ``(value, aux)``: jaxopt minimises the value, and the
        result's ``aux`` is that of its ``x``.

    Returns:
      ``MinimizeResult``. Stops when the gradient norm is ``<= tol``, ``patience``
      consecutive steps are ``<= xtol`` (a failed line search restarts the L-BFGS memory and
      can give one null step that is not yet convergence), the objective becomes non-finite,
      or after ``maxiter`` iterations. Pure: jittable and vmappable.
    """
    objective = fun
    if has_aux:
        def objective(x, *a):
            return fun(x, *a)[0]
    solver = _lbfgs(objective, maxiter, max_stepsize, history_size)
    x0 = jnp.asarray(x0)
    state0 = solver.init_state(x0, *args)
    hist0 = jnp.full((int(maxiter) + 1,), jnp.nan, state0.value.dtype).at[0].set(state0.value)
    tol = jnp.asarray(tol, x0.dtype)
    xtol = jnp.asarray(xtol, x0.dtype)

    def cond(c: _Carry):
        return (~c.done) & (c.it < maxiter)

    def body(c: _Carry) -> _Carry:
        x_new, state_new = solver.update(c.x, c.state, *args)
        ok = jnp.isfinite(state_new.value) & jnp.all(jnp.isfinite(x_new))
        step = jnp.where(ok, jnp.linalg.norm(x_new - c.x), jnp.zeros((), x0.dtype))
        x_new = jnp.where(ok, x_new, c.x)
        state_new = jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), state_new, c.state)
        hist = c.hist.at[c.it + 1].set(jnp.where(ok, state_new.value, jnp.nan))
        stalls = jnp.where(step <= xtol, c.stalls + 1, 0)
        done = (~ok) | (state_new.error <= tol) | (stalls >= patience)
        return _Carry(x_new, state_new, hist, c.it + 1, done, stalls, ~ok)

    init = _Carry(x0, state0, hist0, jnp.int32(0), state0.error <= tol, jnp.int32(0), jnp.bool_(False))
    c = jax.lax.while_loop(cond, body, init)
    x, state, hist, it, stalls, bad = c.x, c.state, c.hist, c.it, c.stalls, c.bad
    value, aux = fun(x, *args) if has_aux else (fun(x, *args), None)
    # converged: small gradient or stalled steps, never by running out of iterations while
    # still moving, and never after a non-finite objective
    converged = (jnp.isfinite(value) & ~bad) & ((state.error <= tol) | (stalls >= patience))
    return MinimizeResult(x=x, value=value, history=hist, num_iterations=it,
                          converged=converged, grad_norm=state.error, aux=aux)
