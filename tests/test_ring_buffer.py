"""Ring buffer of training records: fills invalid records from earlier frames, never emits an invalid one."""

from __future__ import annotations

import pytest
import torch

from nrc.errors import ConfigError
from nrc.render.radiance_caching.ring_buffer import RingBuffer, TrainingRecords


def frame(gen: torch.Generator, n: int, p_valid: float, tag: float = 0.0) -> tuple[TrainingRecords, torch.Tensor]:
    """Random records; invalid ones carry NaN targets. ``tag`` goes into every position's x."""
    valid = torch.rand(n, generator=gen) < p_valid
    pos = torch.rand(n, 3, generator=gen)
    pos[:, 0] = tag
    targets = torch.rand(n, 3, generator=gen)
    targets[~valid] = float("nan")
    return TrainingRecords(pos, torch.randn(n, 3, generator=gen), targets), valid


def tagged(n: int, start: int) -> TrainingRecords:
    """``n`` records whose every component is its sequence number ``start + i``."""
    v = torch.arange(start, start + n, dtype=torch.float32)[:, None].expand(n, 3).contiguous()
    return TrainingRecords(v, v.clone(), v.clone())


def test_fill_keeps_size_and_never_emits_invalid() -> None:
    gen = torch.Generator().manual_seed(0)
    ring = RingBuffer(50)
    for step, p_valid in enumerate((0.0, 0.3, 0.0, 0.9, 0.5, 0.1, 1.0, 0.0)):
        records, valid = frame(gen, 64, p_valid, tag=float(step))
        out = ring.fill(records, valid, gen)
        assert all(torch.isfinite(t).all() for t in out)
        if len(ring) == 0:  # nothing stored yet: only the valid records
            assert out.positions.shape[0] == int(valid.sum())
            assert torch.equal(out.targets, records.targets[valid])
        else:
            assert all(t.shape == (64, 3) for t in out)
            for got, given in zip(out, records):
                assert torch.equal(got[valid], given[valid])  # valid records stay in place
            stored = {tuple(r) for r in torch.cat(list(ring.stored()), dim=1).tolist()}
            drawn = torch.cat(list(out), dim=1)[~valid].tolist()
            assert all(tuple(r) in stored for r in drawn)  # replacements come from earlier frames
            assert all(r[0] < step for r in drawn)
        ring.push(records, valid)
    assert len(ring) == 50


def test_draws_are_uniform_over_stored_records() -> None:
    ring = RingBuffer(8)
    ring.push(tagged(8, 0), torch.ones(8, dtype=torch.bool))
    records, valid = tagged(8000, 100), torch.zeros(8000, dtype=torch.bool)
    counts = torch.bincount(ring.fill(records, valid, torch.Generator().manual_seed(1)).targets[:, 0].long(),
                            minlength=8)
    assert counts.shape == (8,) and (counts - 1000).abs().max() < 150


def test_wrap_around_overwrites_oldest() -> None:
    ring = RingBuffer(5)
    ring.push(tagged(3, 0), torch.ones(3, dtype=torch.bool))
    assert ring.stored().targets[:, 0].tolist() == [0, 1, 2]
    valid = torch.tensor([True, False, True, True, True])
    ring.push(tagged(5, 3), valid)  # stores 3, 5, 6, 7; overwrites 0 and 1
    assert len(ring) == 5 and ring.stored().targets[:, 0].tolist() == [2, 3, 5, 6, 7]
    ring.push(tagged(12, 10), torch.ones(12, dtype=torch.bool))  # more than capacity: the newest 5 remain
    assert ring.stored().positions[:, 0].tolist() == [17, 18, 19, 20, 21]
    ring.push(tagged(4, 30), torch.zeros(4, dtype=torch.bool))  # nothing valid: unchanged
    assert ring.stored().directions[:, 0].tolist() == [17, 18, 19, 20, 21]


def test_deterministic_with_seeded_generator() -> None:
    def run(seed: int) -> list[torch.Tensor]:
        gen, ring, outs = torch.Generator().manual_seed(seed), RingBuffer(40), []
        for _ in range(5):
            records, valid = frame(gen, 32, 0.5)
            outs.extend(ring.fill(records, valid, gen))
            ring.push(records, valid)
        return outs

    a, b, c = run(3), run(3), run(4)
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(x.shape == y.shape and torch.equal(x, y) for x, y in zip(a, c))


def test_state_round_trip() -> None:
    gen = torch.Generator().manual_seed(5)
    ring = RingBuffer(20)
    for _ in range(3):
        ring.push(*frame(gen, 16, 0.7))
    restored = RingBuffer(20)
    restored.load_state_dict(ring.state_dict())
    assert len(restored) == len(ring)
    assert all(torch.equal(x, y) for x, y in zip(restored.stored(), ring.stored()))
    records, valid = frame(gen, 16, 0.5)
    ring.push(records, valid)
    restored.push(records, valid)
    assert all(torch.equal(x, y) for x, y in zip(restored.stored(), ring.stored()))  # same oldest overwritten
    # a full, wrapped ring fills invalid records from the same slots after a restore (an exact resume)
    again = RingBuffer(20)
    again.load_state_dict(ring.state_dict())
    records, valid = frame(gen, 16, 0.3)
    fills = [r.fill(records, valid, torch.Generator().manual_seed(9)) for r in (ring, again)]
    assert all(torch.equal(x, y) for x, y in zip(*fills))
    with pytest.raises(ConfigError, match=r"ring_buffer holds 10 records, the checkpoint's ring 20: resume with "
                                          r"renderer.training.ring_buffer=20"):
        RingBuffer(10).load_state_dict(ring.state_dict())
    with pytest.raises(ConfigError, match="ring_buffer.capacity"):
        RingBuffer(0)
