"""Otsu threshold in JAX equals scikit-image's, bin for bin."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from skimage.exposure import histogram as sk_histogram
from skimage.filters import threshold_otsu as sk_otsu

from cm3d.ops import otsu

CAP = 256  # inputs are padded to one shape (invalid tail) so hypothesis compiles once per nbins
_otsu = jax.jit(otsu.threshold_otsu, static_argnums=1)


def _padded(x):
    x = np.asarray(x, np.float32)
    buf = np.full(CAP, 7.0, np.float32)  # the padding value must not matter
    buf[: x.size] = x
    return buf, np.arange(CAP) < x.size


# no subnormals: XLA on CPU (and GPU) flushes them to zero, so -1e-45 falls in the bin of 0.0 where
# NumPy puts it one bin lower (a platform property, documented in cm3d.ops.otsu)
finite32 = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False, allow_subnormal=False, width=32)


@st.composite
def samples(draw):
    kind = draw(st.sampled_from(["floats", "levels", "bimodal"]))
    n = draw(st.integers(2, CAP))
    if kind == "floats":
        return np.array(draw(st.lists(finite32, min_size=n, max_size=n)), np.float32)
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    if kind == "levels":  # few distinct values: ties in the between-class variance
        return (rng.integers(0, draw(st.integers(2, 6)), n) * draw(st.floats(1e-3, 1e3))).astype(np.float32)
    return np.concatenate([rng.normal(0, 1, n), rng.normal(rng.uniform(1, 20), rng.uniform(0.1, 4), n // 2)]
                          )[:n].astype(np.float32) * np.float32(10.0 ** rng.uniform(-4, 4))


@settings(max_examples=150, deadline=None)
@given(x=samples(), nbins=st.sampled_from([2, 3, 16, 100, 256]))
def test_equals_skimage(x, nbins):
    buf, valid = _padded(x)
    ours = float(_otsu(buf, nbins, valid))
    ref = float(sk_otsu(x, nbins=nbins))
    assert ours == ref


def test_histogram_equals_skimage():
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = (rng.standard_t(3, 1000) * 10.0 ** rng.uniform(-3, 3)).astype(np.float32)
        counts, centres = jax.jit(otsu.histogram, static_argnums=1)(x, 100)
        ref_counts, ref_centres = sk_histogram(x, 100, source_range="image")
        np.testing.assert_array_equal(counts, ref_counts)
        np.testing.assert_array_equal(centres, ref_centres)


def test_image_and_valid_mask():
    rng = np.random.default_rng(1)
    img = np.concatenate([rng.normal(0, 1, (10, 16)), rng.normal(6, 1, (6, 16))]).astype(np.float32)
    mask = rng.random(img.shape) < 0.6
    both = jax.jit(lambda a, m: (otsu.threshold_otsu(a, 256), otsu.threshold_otsu(a, 256, m)))(img, mask)
    assert float(both[0]) == float(sk_otsu(img))
    assert float(both[1]) == float(sk_otsu(img[mask]))


def test_graceful_paths():
    const, valid = _padded(np.full(25, 2.5, np.float32))
    assert float(_otsu(const, 256, valid)) == 2.5  # a single value, as scikit-image returns it
    assert float(_otsu(const, 256, np.zeros(CAP, bool))) == 0.0  # nothing valid
    x = np.array([0.0, 1.0, np.nan, np.inf, 0.2, 0.9, -np.inf], np.float32)
    buf, valid = _padded(x)
    assert float(_otsu(buf, 256, valid)) == float(sk_otsu(x[np.isfinite(x)]))  # non-finite left out
    with pytest.raises(ValueError):
        otsu.threshold_otsu(x, nbins=1)


def test_jit_vmap_invariance():
    rng = np.random.default_rng(2)
    xs = np.stack([np.concatenate([rng.normal(0, 1, 300), rng.normal(k + 3, 1, 100)]) for k in range(4)])
    xs = xs.astype(np.float32)
    batched = jax.jit(jax.vmap(otsu.threshold_otsu, in_axes=(0, None)), static_argnums=1)(xs, 64)
    single = jax.jit(otsu.threshold_otsu, static_argnums=1)
    for i in range(4):
        assert float(batched[i]) == float(single(xs[i], 64)) == float(sk_otsu(xs[i], nbins=64))
    assert jnp.isfinite(batched).all()
