"""GigE Vision block-id unwrapping (pure function)."""

from drivers.genicam_util import unwrap_block_id


def _unwrap(raws):
    out, last = [], None
    for r in raws:
        u = unwrap_block_id(r, last)
        out.append(u)
        last = u if last is None else max(last, u)
    return out


def test_wrap_65535_to_1_is_contiguous():
    assert _unwrap([65533, 65534, 65535, 1, 2]) == [65533, 65534, 65535, 65536, 65537]
    # twice round the clock
    raws = [(i - 1) % 65535 + 1 for i in range(65530, 65530 + 2 * 65535)]
    out = _unwrap(raws)
    assert out == list(range(65530, 65530 + 2 * 65535))


def test_late_buffer_across_the_wrap_lands_below_not_a_lap_ahead():
    # 65534 completes after 1 and 2 (a retried frame): it must not look a lap ahead
    assert _unwrap([65533, 65535, 1, 2, 65534, 3]) == [65533, 65535, 65536, 65537, 65534, 65538]


def test_64_bit_ids_pass_through():
    assert _unwrap([70000, 70001, 70003]) == [70000, 70001, 70003]
