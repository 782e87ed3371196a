"""Hostile inputs of an independent round before issue 47's (found outside the repository, kept here as generated variants)."""
from __future__ import annotations

import numpy as np
import pytest

from kiloforge import numfmt
from kiloforge.actors.dense import dense_weights

_RNG = np.random.default_rng(np.random.SeedSequence(20261206))
#: (e_in, e_out, f): a zero weight row whose bias lands at -(2^31 + f * 2^(shift-1)), where the rounding constant
#: would bring |b + 2^(shift-1)| back under 2^31 although b itself is no int32
BIAS_EDGE = [(int(_RNG.integers(0, 8)), int(_RNG.integers(0, 8)), float(_RNG.uniform(0.01, 0.99))) for _ in range(8)]


@pytest.mark.parametrize("e_in,e_out,f", BIAS_EDGE)
def test_bias_beyond_int32_is_never_wrapped(e_in, e_out, f):
    """A bias just beyond int32 next to all-zero weights is rescaled (or refused), never wrapped to the other sign."""
    W = np.zeros((2, 5))
    W[1] = np.linspace(-1.0, 1.0, 5)
    shift_max = numfmt.MAX_SHIFT
    b = np.array([-(2.0 ** 31 + f * 2.0 ** (shift_max - 1)) / 2.0 ** (shift_max + e_out), 0.1])
    wq, bq, shift, e = dense_weights("layer", W, b, e_in, e_out, may_lower_e_out=True)
    assert bq[0] < 0
    assert int(numfmt.acc_bound(wq, bq, shift).max()) < numfmt.ACC32_LIMIT
    np.testing.assert_allclose(bq[0] * 2.0 ** -(int(shift[0]) + e), b[0], rtol=1e-6)
