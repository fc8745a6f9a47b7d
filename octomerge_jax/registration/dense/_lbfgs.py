"""The minimiser behind the dense alignment: L-BFGS with an Armijo backtracking line search,
written as one ``lax.while_loop`` whose body evaluates ``value_and_grad`` of the objective
once, so the objective is traced and compiled once.

Reference: J. Nocedal and S. J. Wright, *Numerical Optimization*, 2nd ed., Springer 2006:
Alg. 7.4 (the L-BFGS two-loop recursion), eq. 7.20 (the initial scaling ``H_0``), Alg. 3.1
(backtracking line search with the sufficient-decrease condition).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["MinimizeResult", "minimize"]


class MinimizeResult(NamedTuple):
    """Outcome of a minimiser (arrays; batched under ``vmap``)."""

    x: jax.Array               # (n,) final parameters
    value: jax.Array           # () objective at x
    history: jax.Array         # (maxiter + 1,) objective at x_0, x_1, ...; NaN after the last iterate
    num_iterations: jax.Array  # () int32 iterations performed
    converged: jax.Array       # () bool: small gradient or stalled steps, not merely maxiter reached
    grad_norm: jax.Array       # () gradient norm at x
    aux: Any = None            # with has_aux: the objective's auxiliary output at x, else None


class _Memory(NamedTuple):
    """The L-BFGS ring buffer of curvature pairs (``m = history_size``)."""

    S: jax.Array       # (m, n) steps s_i = x_{i+1} - x_i
    Y: jax.Array       # (m, n) gradient changes y_i = g_{i+1} - g_i
    rho: jax.Array     # (m,) 1 / s_i.y_i
    valid: jax.Array   # (m,) bool, the slot holds a pair
    newest: jax.Array  # () int32, slot of the latest pair
    gamma: jax.Array   # () H_0 = gamma I (s.y / y.y of the latest pair)


class _State(NamedTuple):
    """Carry of ``minimize``'s ``while_loop``: one evaluation per step."""

    x: jax.Array           # (n,) current iterate
    f: jax.Array           # () objective at x (inf before the first evaluation)
    g: jax.Array           # (n,) gradient at x
    d: jax.Array           # (n,) search direction from x
    a: jax.Array           # () step fraction: the next trial point is x + a d
    memory: _Memory
    it: jax.Array          # () int32, accepted steps
    evals: jax.Array       # () int32, objective evaluations
    backtracks: jax.Array  # () int32, halvings of the current line search
    stalls: jax.Array      # () int32, consecutive accepted steps shorter than xtol
    started: jax.Array     # () bool, x has been evaluated
    done: jax.Array        # () bool
    converged: jax.Array   # () bool
    bad: jax.Array         # () bool, the objective is not finite at x0
    hist: jax.Array        # (maxiter + 1,) objective after every accepted step
    aux: Any = None        # with has_aux: the objective's auxiliary output at x


def _empty_memory(m: int, n: int, dt) -> _Memory:
    return _Memory(S=jnp.zeros((m, n), dt), Y=jnp.zeros((m, n), dt), rho=jnp.zeros((m,), dt),
                   valid=jnp.zeros((m,), bool), newest=jnp.int32(m - 1), gamma=jnp.ones((), dt))


def _remember(mem: _Memory, s, y, accept) -> _Memory:
    """Store the pair ``(s, y)`` of an accepted step when its curvature ``s.y`` is positive."""
    m = mem.S.shape[0]
    sy = jnp.dot(s, y)
    store = accept & (sy > 1e-10 * jnp.dot(y, y))
    k = (mem.newest + 1) % m
    return _Memory(S=jnp.where(store, mem.S.at[k].set(s), mem.S),
                   Y=jnp.where(store, mem.Y.at[k].set(y), mem.Y),
                   rho=jnp.where(store, mem.rho.at[k].set(1.0 / jnp.where(store, sy, 1.0)), mem.rho),
                   valid=jnp.where(store, mem.valid.at[k].set(True), mem.valid),
                   newest=jnp.where(store, k, mem.newest),
                   gamma=jnp.where(store, sy / jnp.dot(y, y), mem.gamma))


def _forget(mem: _Memory, restart) -> _Memory:
    """Clear the memory where ``restart`` (a failed quasi-Newton line search)."""
    reset = lambda a: jnp.where(restart, jnp.zeros_like(a), a)  # noqa: E731
    return _Memory(S=reset(mem.S), Y=reset(mem.Y), rho=reset(mem.rho),
                   valid=jnp.where(restart, jnp.zeros_like(mem.valid), mem.valid), newest=mem.newest,
                   gamma=jnp.where(restart, jnp.ones_like(mem.gamma), mem.gamma))


def _two_loop(g, mem: _Memory):
    """L-BFGS two-loop recursion (Nocedal & Wright Alg. 7.4): ``-H g`` with ``H_0 = gamma I``."""
    S, Y, rho, valid, newest = mem.S, mem.Y, mem.rho, mem.valid, mem.newest
    m = S.shape[0]

    def first(i, carry):
        q, alpha = carry
        j = (newest - i) % m
        a = jnp.where(valid[j], rho[j] * jnp.dot(S[j], q), 0.0)
        return q - a * Y[j], alpha.at[j].set(a)

    q, alpha = jax.lax.fori_loop(0, m, first, (g, jnp.zeros_like(rho)))
    r = mem.gamma * q

    def second(i, r):
        j = (newest + 1 + i) % m
        b = jnp.where(valid[j], rho[j] * jnp.dot(Y[j], r), 0.0)
        return r + jnp.where(valid[j], alpha[j] - b, 0.0) * S[j]

    return -jax.lax.fori_loop(0, m, second, r)


def _step(c: _State, ft, gt, aux_t, *, xtol, tol, init_step, armijo, max_backtracks, patience) -> _State:
    """One evaluation ``(ft, gt)`` (and the objective's auxiliary output ``aux_t``) at the trial
    point ``c.x + c.a c.d``: accept it (new iterate, curvature pair, quasi-Newton direction) or
    halve the step; after ``max_backtracks`` halvings restart along ``-g`` with an empty memory,
    or give up if that was already steepest descent."""
    dt = c.x.dtype
    xt = c.x + c.a * c.d
    finite = jnp.isfinite(ft) & jnp.all(jnp.isfinite(gt))
    gd = jnp.dot(c.g, c.d)
    accept = c.started & finite & (ft <= c.f + armijo * c.a * gd)
    first = ~c.started
    moved = accept | first
    # --- accepted step (or the initial evaluation): new iterate and curvature pair
    s = xt - c.x
    mem = _remember(c.memory, s, gt - c.g, accept)
    x = jnp.where(moved, xt, c.x)
    f = jnp.where(moved, ft, c.f)
    g = jnp.where(moved, gt, c.g)
    aux = jax.tree_util.tree_map(lambda a, b: jnp.where(moved, a, b), aux_t, c.aux)
    it = c.it + accept.astype(jnp.int32)
    hist = jnp.where(first, c.hist.at[0].set(ft), jnp.where(accept, c.hist.at[it].set(ft), c.hist))
    step = jnp.linalg.norm(s)
    stalls = jnp.where(accept, jnp.where(step <= xtol, c.stalls + 1, 0), c.stalls)
    steepest = lambda g: -g * (init_step / jnp.maximum(jnp.linalg.norm(g), 1e-30))  # noqa: E731
    d_qn = _two_loop(g, mem)
    d_qn = jnp.where(jnp.any(mem.valid) & (jnp.dot(d_qn, g) < 0), d_qn, steepest(g))
    # --- rejected step: halve; after max_backtracks, restart along -g (or give up)
    fail = c.started & ~accept & (c.backtracks + 1 > max_backtracks)
    was_steepest = ~jnp.any(c.memory.valid)
    restart = fail & ~was_steepest
    give_up = fail & was_steepest
    mem = _forget(mem, restart)
    d = jnp.where(moved, d_qn, jnp.where(restart, steepest(g), c.d))
    a = jnp.where(moved | restart, jnp.ones((), dt), 0.5 * c.a)
    backtracks = jnp.where(moved | restart, 0, c.backtracks + 1)
    bad = first & ~finite
    small = moved & (jnp.linalg.norm(g) <= tol)
    converged = small | (stalls >= patience) | give_up
    return _State(x=x, f=f, g=g, d=d, a=a, memory=mem, it=it, evals=c.evals + 1,
                  backtracks=backtracks, stalls=stalls, started=jnp.bool_(True),
                  done=bad | converged, converged=converged & ~bad, bad=bad, hist=hist, aux=aux)


def minimize(fun: Callable, x0, *args, maxiter: int, tol=1e-4, xtol=1e-5, init_step=1.0,
             history_size: int = 6, patience: int = 3, max_backtracks: int = 8,
             armijo: float = 1e-4, has_aux: bool = False) -> MinimizeResult:
    """Minimise the scalar ``fun(x, *args)`` from ``x0 (n,)`` with L-BFGS and an Armijo
    backtracking line search, as one ``lax.while_loop`` that evaluates ``value_and_grad(fun)``
    once per step (at the initial point, at a trial step or at a halved step).

    The first trial step has length ``init_step`` (units of ``x``) along ``-g``; later ones
    are the quasi-Newton step ``-H g`` (``H_0 = s.y / y.y``, Nocedal & Wright eq. 7.20),
    halved up to ``max_backtracks`` times until ``f`` decreases by ``armijo * step * g.d``.
    A failed line search clears the memory and retries along ``-g`` from ``init_step``; if
    even that fails the point is a minimum at the resolution of the search (a kink of a
    piecewise-smooth objective) and counts as converged. Curvature pairs with ``s.y <= 0``
    are skipped.

    Args:
      fun: scalar objective ``fun(x, *args)``, differentiable in ``x``.
      x0: ``(n,)`` start.
      maxiter: accepted steps at most (static).
      tol: gradient-norm tolerance (may be traced).
      xtol: Euclidean step length below which a step counts as stalled (may be traced).
      init_step: length of steepest-descent trial steps, units of ``x`` (may be traced).
      history_size, patience, max_backtracks: static; ``patience`` stalled steps in a row stop.
      armijo: sufficient-decrease constant.
      has_aux: static; ``fun`` returns ``(value, aux)`` (``aux`` a pytree of arrays, no
        gradient), and the result's ``aux`` is that of its ``x`` (an objective evaluated
        once for its value and its by-products).

    Returns:
      ``MinimizeResult``. Stops on ``|g| <= tol``, on ``patience`` consecutive accepted steps
      shorter than ``xtol``, on a failed steepest-descent search, on a non-finite objective at
      ``x0``, after ``maxiter`` accepted steps or ``(max_backtracks + 2) * maxiter``
      evaluations. Pure: jittable and vmappable.
    """
    x0 = jnp.asarray(x0)
    n, m, dt = x0.shape[0], int(history_size), x0.dtype
    vg = jax.value_and_grad(fun, has_aux=has_aux)
    rules = dict(tol=jnp.asarray(tol, dt), xtol=jnp.asarray(xtol, dt), init_step=jnp.asarray(init_step, dt),
                 armijo=armijo, max_backtracks=max_backtracks, patience=patience)
    max_evals = (int(max_backtracks) + 2) * int(maxiter) + 1
    zero = jnp.zeros((), dt)
    init = _State(x=x0, f=jnp.asarray(jnp.inf, dt), g=jnp.zeros_like(x0), d=jnp.zeros_like(x0), a=zero,
                  memory=_empty_memory(m, n, dt), it=jnp.int32(0), evals=jnp.int32(0),
                  backtracks=jnp.int32(0), stalls=jnp.int32(0), started=jnp.bool_(False),
                  done=jnp.bool_(False), converged=jnp.bool_(False), bad=jnp.bool_(False),
                  hist=jnp.full((int(maxiter) + 1,), jnp.nan, dt))
    if has_aux:  # NaN (or zero) until the first evaluation, of the shapes fun returns
        shapes = jax.eval_shape(lambda x: fun(x, *args)[1], x0)
        init = init._replace(aux=jax.tree_util.tree_map(
            lambda s: jnp.full(s.shape, jnp.nan if jnp.issubdtype(s.dtype, jnp.floating) else 0, s.dtype), shapes))

    def cond(c):
        return (~c.done) & (c.it < maxiter) & (c.evals < max_evals)

    def body(c):
        value, gt = vg(c.x + c.a * c.d, *args)
        ft, aux_t = value if has_aux else (value, None)
        return _step(c, ft, gt, aux_t, **rules)

    c = jax.lax.while_loop(cond, body, init)
    return MinimizeResult(x=c.x, value=c.f, history=c.hist, num_iterations=c.it,
                          converged=c.converged, grad_norm=jnp.linalg.norm(c.g), aux=c.aux)
