"""Behaviour unchanged: fixed-key renders and a fit against recorded values
(`tests/_golden.py`, `tests/data/golden.npz`).

Tolerance: the recorded values came from the same code on the same CPU backend, so a pure
refactor reproduces them bit for bit; we allow float32 round-off (rtol 1e-5 of the image's
largest value) so that a change of summation order inside XLA (e.g. a fused reduction
after code moved) does not fail it, while any change of sampling or weighting (a different
random draw, a missed technique, a changed MIS weight) moves pixels by far more.
"""

from __future__ import annotations

import numpy as np
import pytest

from .. import _golden as G

RECORDED = dict(np.load(G.PATH))


def _close(name, got):
    want = RECORDED[name]
    assert got.shape == want.shape and got.dtype == want.dtype, (got.shape, want.shape)
    scale = float(np.max(np.abs(want)))
    assert scale > 0, f"{name}: the recorded reference is all zero (useless)"
    err = float(np.max(np.abs(got.astype(np.float64) - want)))
    assert err <= 1e-5 * scale, f"{name}: max |diff| {err:.3g} vs scale {scale:.3g}"


@pytest.mark.parametrize("name", list(G.RENDERS))
def test_fixed_key_render_unchanged(name):
    _close(name, G.render_case(name))


def test_fixed_key_spectral_unchanged():
    _close("spectral_hero_pool", G.spectral_case())


def test_fixed_key_fit_unchanged():
    _close("fit_pool_sky", G.fit_case())
