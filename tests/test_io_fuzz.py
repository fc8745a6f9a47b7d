"""Fuzzing the OctoMap readers: mutated or truncated files give a valid map or MapFormatError,
never another exception, a hang or a partial map."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from octomerge_jax import morton
from octomerge_jax.io import MapFormatError, from_bytes, load, read_header, to_bytes
from octomerge_jax.map import from_leaves

import fuzz_inputs


def _sample_map():
    rng = np.random.default_rng(0)
    keys = np.unique(rng.integers(32768 - 40, 32768 + 40, size=(300, 3)), axis=0)
    codes = morton.keys_to_codes(keys.astype(np.uint16))
    # a few coarser leaves: an aligned 8^3 block of equal values becomes one depth-13 leaf
    block = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3)
    block_codes = morton.keys_to_codes((block + 32768 + 64).astype(np.uint16))
    codes = np.concatenate([codes, block_codes[:1]])
    depths = np.concatenate([np.full(keys.shape[0], 16), [13]])
    values = rng.normal(size=codes.size).astype(np.float32)
    return from_leaves(codes, depths, values, 0.05)


_MAP = _sample_map()
_IMAGES = {ext: to_bytes(_MAP, binary=(ext == "bt"), header=True) for ext in ("bt", "ot")}
_DIR = Path(tempfile.mkdtemp(prefix="octomerge_fuzz_"))

mutation = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0, 1)),
    st.tuples(st.just("set"), st.floats(0, 1), st.integers(0, 255)),
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(0, 7)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=8)),
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 16)),
)


def _mutate(data: bytes, ops, header_bias: bool) -> bytes:
    buf = bytearray(data)
    for op in ops:
        # half the time aim at the ~130-byte header, where parsing is most delicate
        span = min(len(buf), 140) if header_bias else len(buf)
        pos = min(int(op[1] * span), max(len(buf) - 1, 0))
        if op[0] == "truncate":
            del buf[pos:]
        elif not buf:
            continue
        elif op[0] == "set":
            buf[pos] = op[2]
        elif op[0] == "flip":
            buf[pos] ^= 1 << op[2]
        elif op[0] == "insert":
            buf[pos:pos] = op[2]
        else:
            del buf[pos:pos + op[2]]
    return bytes(buf)


def _assert_valid(m):
    lv = m.leaves()
    assert np.all((lv.depths >= 0) & (lv.depths <= 16))
    assert not np.isnan(lv.log_odds).any()
    from_leaves(lv.codes, lv.depths, lv.log_odds, m.resolution, check=True)  # disjoint, aligned
    assert m.resolution > 0


@pytest.mark.parametrize("ext", ["bt", "ot"])
@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(ops=st.lists(mutation, min_size=1, max_size=4), header_bias=st.booleans())
def test_mutated_files_load_or_raise_map_format_error(ext, ops, header_bias):
    data = _mutate(_IMAGES[ext], ops, header_bias)
    path = _DIR / f"fuzz.{ext}"
    path.write_bytes(data)
    try:
        m = load(path)
    except MapFormatError as err:
        assert str(path) in str(err)
        assert err.offset is None or 0 <= err.offset <= len(data)
        return
    _assert_valid(m)


@pytest.mark.parametrize("binary", [True, False])
@settings(max_examples=150, deadline=None)
@given(ops=st.lists(mutation, min_size=1, max_size=4))
def test_mutated_payloads_load_or_raise_map_format_error(binary, ops):
    image = _IMAGES["bt" if binary else "ot"]
    body = image[read_header_offset(binary):]
    data = _mutate(body, ops, header_bias=False)
    try:
        m = from_bytes(data, binary=binary, resolution=0.05)
    except MapFormatError as err:
        assert str(err).startswith("<bytes>")
        return
    _assert_valid(m)


def read_header_offset(binary: bool) -> int:
    path = _DIR / ("h.bt" if binary else "h.ot")
    path.write_bytes(_IMAGES["bt" if binary else "ot"])
    return read_header(path).data_offset


@settings(max_examples=100, deadline=None)
@given(data=st.binary(max_size=64), binary=st.booleans())
def test_random_payloads(data, binary):
    try:
        m = from_bytes(data, binary=binary, resolution=0.1)
    except MapFormatError:
        return
    _assert_valid(m)


def test_unmutated_images_load():
    for ext, data in _IMAGES.items():
        path = _DIR / f"clean.{ext}"
        path.write_bytes(data)
        assert load(path).num_leaves > 0


# ----------------------------------------------------------------------------- campaign slice
# A small seeded slice of the fuzz campaign (tests/fuzz_inputs.py; run it for longer as a
# script): mutated maps, scan files, manifests and configs give a result or a documented
# one-line error naming the file; ``info`` / ``convert`` on mutated maps exit 0 or 1 with one
# error line and leave no file behind.


@pytest.mark.parametrize("targets, cli, cases", [
    (("bt", "ot"), True, 12),
    (("graph", "pcd", "dat"), False, 40),
    (("toml", "json"), False, 40),
])
def test_fuzz_campaign_slice(targets, cli, cases):
    res = fuzz_inputs.campaign(seed=7, cases=cases, targets=targets, cli=cli, timeout=60)
    assert res["failures"] == []
    for t in targets:
        assert sum(res["counts"][t].values()) == cases


def test_fuzz_campaign_slice_manifests():
    res = fuzz_inputs.campaign(seed=7, cases=40, targets=("manifest",))
    assert res["failures"] == []
