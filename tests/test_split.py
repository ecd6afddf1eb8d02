"""diagnose's training and held-out blocks (issue 17, part 4): every part of the log, the
loop open under a modulation and the loop closed, is held out in its last third, so an
actuator effect fitted on the modulation is also judged on it."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np

from leveler.analysis.diagnose import MIN_PART_S, split
from leveler.analysis.whittle import Whitener, fast_length

RATE_HZ = 10.0


def _log(engaged: np.ndarray | None, n: int) -> SimpleNamespace:
    return SimpleNamespace(y_m=np.zeros(n), engaged=engaged, dt_s=1.0 / RATE_HZ)


def _samples(seconds: float) -> int:
    return int(seconds * RATE_HZ)


def test_a_modulated_log_is_held_out_in_both_its_parts() -> None:
    n, opened, skip = _samples(3 * 3600), _samples(3600), _samples(300)
    on = np.arange(n) >= opened
    train, test = split(_log(on, n), skip)
    first, second = 2 * (opened - skip) // 3, 2 * (n - opened) // 3
    assert train == [slice(skip, skip + first), slice(opened, opened + second)]
    assert test == [slice(skip + first, opened), slice(opened + second, n)]


def test_a_log_in_one_state_or_of_unknown_state_is_split_two_to_one() -> None:
    n, skip = _samples(2 * 3600), _samples(300)
    cut = skip + 2 * (n - skip) // 3
    for engaged in (None, np.ones(n, dtype=bool)):
        assert split(_log(engaged, n), skip) == ([slice(skip, cut)], [slice(cut, n)])


def test_parts_too_short_to_say_anything_alone_are_joined_to_a_neighbour() -> None:
    """A 5 min opening in the middle (a fault, a hand on the knob) and a short closed
    stretch at the start do not make blocks of their own; the blocks still tile the log."""
    n, skip = _samples(3 * 3600), 0
    on = np.ones(n, dtype=bool)
    on[_samples(600):_samples(3600)] = False  # 10 min closed, then 50 min open
    on[_samples(7200):_samples(7500)] = False  # 5 min open
    train, test = split(_log(on, n), skip)
    assert len(train) == len(test) == 2
    edges = sorted([(s.start, s.stop) for s in train + test])
    assert edges[0][0] == 0 and edges[-1][1] == n
    assert all(a[1] == b[0] for a, b in itertools.pairwise(edges))
    assert all((s.stop - s.start) / RATE_HZ >= MIN_PART_S / 3 for s in test)
    assert train[0] == slice(0, 2 * _samples(3600) // 3)  # the short start joined the opening


def _largest_factor_at_most(m: int, p_max: int) -> bool:
    for p in (2, 3, 5, 7, 11):
        while p <= p_max and m % p == 0:
            m //= p
    return m == 1


def test_a_block_is_cut_to_a_length_the_fft_does_fast() -> None:
    """A 24 h log's closed-loop block of 384,576 samples (2^6 x 3 x 2003) transforms ~14x
    slower than one of 384,160 (2^5 x 5 x 7^4), which is 1.8x slower than 384,000 (2^10 x
    3 x 5^3): blocks lose under 1 % of their end (under 0.5 % for factors of 2, 3 and 5
    alone), and every sample of what is left is used."""
    assert fast_length(384576) == 384000
    assert fast_length(860160) == 860160  # 2^13 x 3 x 5 x 7: no 5-smooth length in reach
    assert fast_length(2 ** 10 * 3 ** 2 * 11) == 2 * 3 ** 4 * 5 ** 4  # 0.12 % shorter
    assert fast_length(17) == 16 and fast_length(1) == 1
    for n in (2003, 23908, 191424, 384576, 860161, 864001):
        m = fast_length(n)
        assert 0.99 * n <= m <= n
        assert _largest_factor_at_most(m, 11)
        if not _largest_factor_at_most(m, 5):  # only where none is within 0.5 %
            assert not any(_largest_factor_at_most(k, 5) for k in range(int(0.995 * n), n + 1))
    w = Whitener(slice(100, 100 + 191424), 200000, 0.1, lambda f: np.ones_like(f))
    assert w.span == slice(100, 100 + fast_length(191424)) and w.n == fast_length(191424)
    assert len(w.f_hz) == w.n // 2 + 1
