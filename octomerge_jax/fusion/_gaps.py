"""Gap cells in closed form: a Morton interval ``[s, e)`` cut into the minimal set of aligned
octree cells (at most 7 per level and side), counted and enumerated from the octal digits
of ``-s`` and ``e`` (digit sums, no loop over levels). A *gap* is the part of a split leaf
that the finer map does not know (thesis §5.2.3, case 1 inside cases 3 / 4, eq. 5.14).

Intervals are word columns ``(s_hi, s_lo, e_hi, e_lo)``, int32 arrays of any one shape
(``e`` may be 2^48, the end of the volume); everything is elementwise.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .. import morton
from .._ops import materialize

_D = morton.TREE_DEPTH


def _gap_top(sh, sl, eh, el):
    """Top level ``p`` of the canonical decomposition of ``[s, e)`` and helpers: the top octal
    digit where ``s - 1`` and ``e`` differ (16 when ``s = 0``): ``[s, e]`` holds a multiple of
    ``8^k`` exactly for ``k <= p``. Returns ``(nonempty, p, base)``, ``base`` = first
    digit of the level-``p`` cells (``d_p(s - 1) + 1``, or 0 when ``s = 0``)."""
    nonempty = morton.code_less(sh, sl, eh, el)
    zero = (sh == 0) & (sl == 0)
    borrow = sl == 0
    mh = sh - borrow.astype(jnp.int32)
    ml = jnp.where(borrow, morton.WORD_MASK, sl - 1)
    top_bit = morton.top_bit(mh ^ eh, ml ^ el)
    p = jnp.where(zero, _D, jax.lax.div(jnp.maximum(top_bit, 0), 3))
    p = jnp.where(nonempty, p, 0)
    base = jnp.where(zero, 0, morton.code_digit(mh, ml, p) + 1)
    return nonempty, p, base


def _gap_terms(sh, sl, eh, el):
    """The decomposition of ``[s, e)`` into maximal aligned cells, in closed form: ascending
    from ``s``, ``L_k`` cells at each level ``k < p`` where ``L = (-s) mod 8^p`` (octal digits
    ``L_k``); then ``n_mid = d_p(e) - base`` cells at level ``p``; then descending to ``e``,
    ``R_k`` cells at level ``k`` where ``R = e mod 8^p``. Returns ``(nonempty, p, base, L, R,
    n_mid)`` with ``L``, ``R`` as word pairs."""
    nonempty, p, base = _gap_top(sh, sl, eh, el)
    hm, lm = morton.code_low_masks(p)
    neg_h = (-sh - (sl != 0).astype(jnp.int32)) & morton.WORD_MASK
    neg_l = (-sl) & morton.WORD_MASK
    n_mid = morton.code_digit(eh, el, p) - base
    return nonempty, p, base, (neg_h & hm, neg_l & lm), (eh & hm, el & lm), n_mid


def gap_cell_count(sh, sl, eh, el):
    """Number of cells of the canonical decomposition of Morton intervals ``[s, e)`` into
    maximal aligned octree cells (0 for empty intervals): ``digitsum(L) + n_mid +
    digitsum(R)`` (``_gap_terms``), at most 7 per level and side."""
    nonempty, _, _, L, R, n_mid = _gap_terms(sh, sl, eh, el)
    return jnp.where(nonempty, morton.code_digit_sum(*L) + n_mid + morton.code_digit_sum(*R), 0)


def _level_search(xh, xl, y):
    """Largest ``j`` in 0..15 with ``digitsum(x mod 8^j) <= y`` (a 4-step binary search; the
    digit sums of ``x``'s low digits grow with ``j``), and that digit sum."""
    j = jnp.zeros_like(y)
    s = jnp.zeros_like(y)
    for step in (8, 4, 2, 1):
        hm, lm = morton.code_low_masks(j + step)
        v = morton.code_digit_sum(xh & hm, xl & lm)
        ok = v <= y
        j = jnp.where(ok, j + step, j)
        s = jnp.where(ok, v, s)
    return j, s


def gap_cell_info(sh, sl, eh, el, t):
    """The ``t``-th cell (Morton order) of the decomposition of ``[s, e)``, packed in one int32
    (one output, so XLA computes it once): ``level | digit << 5 | from_s << 8``. The cell's
    digits above ``level`` are those of ``s`` (ascending part) or ``e``, its digit at
    ``level`` is ``digit``, the rest are 0 (``cell_code``). ``t`` must be below the count."""
    _, p, base, L, R, n_mid = _gap_terms(sh, sl, eh, el)
    ds_l, ds_r = morton.code_digit_sum(*L), morton.code_digit_sum(*R)
    up = t < ds_l
    mid = ~up & (t < ds_l + n_mid)
    u = t - ds_l - n_mid  # index among the descending cells
    # ascending cell t sits at the level j where the digit sums of L's low digits pass t;
    # descending cell u at the level j where those of R's high digits pass u.
    j, s_j = _level_search(jnp.where(up, L[0], R[0]), jnp.where(up, L[1], R[1]),
                           jnp.where(up, t, ds_r - u - 1))
    # ascending: digit j = d_j(s) + [s mod 8^j != 0] + i; descending: digit j = i;
    # middle (level p): digit p = base + i
    d_up = morton.code_digit(sh, sl, j) + morton.code_low_nonzero(sh, sl, j).astype(jnp.int32) + t - s_j
    d_down = u - ds_r + s_j + morton.code_digit(R[0], R[1], j)
    digit = jnp.where(up, d_up, jnp.where(mid, base + t - ds_l, d_down))
    level = jnp.where(mid, p, j)
    return level | jnp.left_shift(jnp.clip(digit, 0, 7), 5) | jnp.left_shift(up.astype(jnp.int32), 8)


def cell_code(sh, sl, eh, el, info):
    """``(hi, lo, depth)`` of a cell from ``gap_cell_info``."""
    level = info & 31
    digit = jnp.right_shift(info, 5) & 7
    from_s = (jnp.right_shift(info, 8) & 1) == 1
    h, l = morton.code_truncate(jnp.where(from_s, sh, eh), jnp.where(from_s, sl, el),
                                jnp.minimum(level + 1, _D))
    h, l = morton.code_put_digit(h, l, jnp.minimum(level, _D - 1), digit)
    whole = level >= _D  # [0, 2^48): the root cell
    return jnp.where(whole, 0, h), jnp.where(whole, 0, l), _D - level


def gap_cell_once(gate, bounds, t):
    """The ``t``-th cell ``(hi, lo, depth)`` (Morton order) of the decompositions of the
    intervals ``bounds() = (s_hi, s_lo, e_hi, e_lo)`` (a function: its
    gathers run inside), the bounds and the cells' closed form computed once into memory
    (``materialize`` on a traced True ``gate``), not once per consumer (the code, depth and
    value scatters)."""
    def once():
        b = bounds()
        return b + (gap_cell_info(*b, t),)

    *b, info = materialize(gate, once)
    return cell_code(*b, info)
