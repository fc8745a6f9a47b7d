"""registration.consensus: choosing among pairwise candidate poses by the agreement of the other
pairs, on synthetic candidates (no maps): wrong best candidates of a symmetric scene (a half
turn, a shifted bay) are replaced by the right ones, a map reached only by an ambiguous pair
stays unplaced, a trusted single pair places its map, and a pair none of whose candidates
agrees is set aside."""

import numpy as np
import pytest

from octomerge_jax import se3
from octomerge_jax.registration.consensus import choose_candidates


def _truth(n, seed=5):
    rng = np.random.default_rng(seed)
    return np.stack([np.eye(4)] + [se3.from_xyz_rpy(*rng.uniform(-8, 8, 2), 0.0, 0.0, 0.0,
                                                     rng.uniform(-np.pi, np.pi), xp=np) for _ in range(n - 1)])


def _rel(T, a, b, noise=0.0, rng=None):
    Z = np.linalg.inv(T[a]) @ T[b]
    if noise:
        Z = Z @ se3.se3_exp(np.concatenate([rng.normal(0, noise, 3), rng.normal(0, noise / 10, 3)]), xp=np)
    return Z


def _half_turn(Z, e=0):
    """``Z`` turned by pi about a vertical axis a few metres off, one axis per pair ``e``: the
    twin pose of a pair whose common region is symmetric (the maps themselves are not)."""
    return Z @ se3.from_xyz_rpy(3.0 + e, 1.0 - 0.5 * e, 0.0, 0.0, 0.0, np.pi, xp=np)


def _shifted(Z, d=5.0):
    return Z @ se3.from_xyz_rpy(d, 0.0, 0.0, 0.0, 0.0, 0.0, xp=np)


def test_wrong_best_candidates_replaced_by_agreement():
    rng = np.random.default_rng(0)
    T = _truth(4)
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    cands, trusted, want = [], [], []
    for e, (a, b) in enumerate(edges):
        Z = _rel(T, a, b, 0.02, rng)
        if e == 0:  # ambiguous: the best is a bay off, the truth second
            cands.append([_shifted(Z), Z, _half_turn(Z, e)])
            trusted.append(False)
            want.append(1)
        elif e == 2:  # called "ok" but turned by pi: the truth is the third candidate
            cands.append([_half_turn(Z, e), _shifted(Z, -6.0), Z])
            trusted.append(True)
            want.append(2)
        else:
            cands.append([Z, _half_turn(Z, e)])
            trusted.append(True)
            want.append(0)
    scores = [[1.0 - 0.1 * c for c in range(len(cs))] for cs in cands]
    out = choose_candidates(4, [a for a, _ in edges], [b for _, b in edges], cands, scores, trusted)
    assert out.placed.all()
    np.testing.assert_array_equal(out.choice, want)
    assert (out.support[1:] >= 2).all()
    for k in range(1, 4):
        np.testing.assert_allclose(out.T_0_k[k][:3, 3], T[k][:3, 3], atol=0.2)


@pytest.mark.parametrize("trusted", [False, True])
def test_single_pair_places_only_when_trusted(trusted):
    T = _truth(3)
    Z01, Z12 = _rel(T, 0, 1), _rel(T, 1, 2)
    out = choose_candidates(3, [0, 1], [1, 2], [[Z01, _half_turn(Z01)], [Z12]], [[1.0, 0.9], [1.0]],
                            [trusted, True])
    assert out.placed.tolist() == [True, trusted, trusted]
    assert out.choice.tolist() == ([0, 0] if trusted else [-1, -1])


def test_equal_evidence_for_two_poses_places_nothing():
    # a trusted pair says one pose, an equally strong path through a third map says another:
    # the map is left unplaced rather than guessed
    T = _truth(3)
    Z01, Z02, Z12 = _rel(T, 0, 1), _rel(T, 0, 2), _rel(T, 1, 2)
    out = choose_candidates(3, [0, 0, 1], [1, 2, 2], [[Z01], [_shifted(Z02, 6.0)], [Z12]], [[1.0], [1.0], [1.0]],
                            [True, True, True])
    assert not out.placed[1:].any() and (out.choice == -1).all()


def test_edge_without_an_agreeing_candidate_is_set_aside():
    T = _truth(3)
    Z01, Z02, Z12 = _rel(T, 0, 1), _rel(T, 0, 2), _rel(T, 1, 2)
    bad = [_half_turn(Z12), _shifted(Z12, 7.0)]  # neither candidate is the truth: a weak, ambiguous pair
    out = choose_candidates(3, [0, 0, 1], [1, 2, 2], [[Z01], [Z02], bad], [[1.0], [1.0], [0.4, 0.35]],
                            [True, True, False])
    assert out.placed.all()
    assert out.choice.tolist() == [0, 0, -1]


def test_argument_lengths_checked():
    with pytest.raises(ValueError, match="one entry per edge"):
        choose_candidates(2, [0], [1], [], [], [])
