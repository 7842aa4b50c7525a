"""Otsu's threshold in JAX, bin for bin the same as ``skimage.filters.threshold_otsu``.

For float32 input and the same ``nbins`` the histogram, bin centres and threshold equal
scikit-image's: NumPy's uniform bins over ``[min, max]`` (its edge corrections included), class
weights and means accumulated sequentially in float32 as ``np.cumsum``, the first maximum wins.
``valid`` restricts the histogram; non-finite values are left out. No errors, no NaN: one distinct
value returns it, no valid element returns 0. Integer images: compare on ``x.astype(np.float32)``.
Subnormals count as 0 (XLA flushes them; docs/motion.md).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _sequential_cumsum(x: jnp.ndarray) -> jnp.ndarray:
    """Left-to-right running sums along the last axis, rounding like ``np.cumsum`` (``jnp.cumsum``
    reassociates). Leading axes are independent sums carried by one scan (one loop in the program for
    Otsu's four sums: the unrolled body is most of the cost of compiling it)."""

    def step(carry, xi):
        carry = carry + xi
        return carry, carry

    _, out = jax.lax.scan(step, jnp.zeros(x.shape[:-1], x.dtype), jnp.moveaxis(x, -1, 0), unroll=16)
    return jnp.moveaxis(out, 0, -1)


def _rounded(p: jnp.ndarray, zero: jnp.ndarray) -> jnp.ndarray:
    """``p`` unchanged, but opaque to the compiler, so XLA:CPU cannot fuse a following ``p + c`` into an
    FMA (a different rounding from NumPy's); ``zero`` is a runtime int32 zero."""
    ib = jax.lax.bitcast_convert_type(p, jnp.int32) ^ zero
    return jax.lax.bitcast_convert_type(ib, p.dtype)


def _prepare(x, valid):
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.float32)
    x = x.reshape(-1)
    v = jnp.isfinite(x)
    if valid is not None:
        v = v & jnp.asarray(valid, bool).reshape(-1)
    lo = jnp.min(jnp.where(v, x, jnp.inf))
    hi = jnp.max(jnp.where(v, x, -jnp.inf))
    return x, v, lo, hi


def _histogram(x, v, lo, hi, nbins: int):
    any_valid = jnp.isfinite(lo)
    first = jnp.where(any_valid, lo, 0.0).astype(x.dtype)
    last = jnp.where(any_valid, hi, 1.0).astype(x.dtype)
    same = first == last
    first = jnp.where(same, first - 0.5, first)
    last = jnp.where(same, last + 0.5, last)
    # np.linspace(first, last, nbins + 1, dtype=x.dtype): edge_i = (i * step) + first, rounded twice
    zero = jnp.isnan(first).astype(jnp.int32)
    nb = (jnp.int32(nbins) ^ zero).astype(x.dtype)  # a runtime divisor: no reciprocal rewrite
    delta = last - first
    step = delta / nb

    def edge(i):
        fi = i.astype(x.dtype)
        e = _rounded(jnp.where(step == 0, fi / nb * delta, fi * step), zero) + first
        return jnp.where(i >= nbins, last, e)

    # np.histogram's uniform-bin index, then its corrections within one ulp of an edge
    xs = jnp.where(v, x, first)
    idx = (((xs - first) / delta) * nb).astype(jnp.int32)
    idx = jnp.clip(idx, 0, nbins - 1)
    idx = jnp.where(xs < edge(idx), idx - 1, idx)
    idx = jnp.where((xs >= edge(idx + 1)) & (idx != nbins - 1), idx + 1, idx)
    idx = jnp.clip(idx, 0, nbins - 1)
    counts = jnp.zeros(nbins, jnp.int32).at[idx].add(v.astype(jnp.int32))
    edges = edge(jnp.arange(nbins + 1))
    return counts, (edges[:-1] + edges[1:]) / 2.0


def histogram(x, nbins: int = 256, valid=None):
    """Counts (nbins,) int32 and bin centres (nbins,) of the valid, finite values of ``x``.

    Same bins as ``skimage.exposure.histogram(x[valid], nbins)`` for float input (NumPy's uniform
    bins over the data range; a constant input gets the range ``[v - 0.5, v + 0.5]``).
    """
    if nbins < 1:
        raise ValueError("histogram: nbins must be >= 1")
    return _histogram(*_prepare(x, valid), nbins)


def threshold_from_histogram(counts, centres):
    """Otsu threshold (scalar) of a histogram: the centre maximising the between-class variance
    (empty end bins skipped, as scikit-image; an all-zero histogram returns ``centres[0]``)."""
    c = jnp.asarray(counts).astype(jnp.float32)
    centres = jnp.asarray(centres)
    cs = _rounded(c * centres, jnp.isnan(centres[0]).astype(jnp.int32))
    w1, w2r, s1, s2r = _sequential_cumsum(jnp.stack([c, c[::-1], cs, cs[::-1]]))
    w2 = w2r[::-1]
    m1 = s1 / jnp.where(w1 > 0, w1, 1.0)
    m2 = (s2r / jnp.where(w2r > 0, w2r, 1.0))[::-1]
    var12 = w1[:-1] * w2[1:] * (m1[:-1] - m2[1:]) ** 2
    # bins before the first / after the last non-empty one do not exist for scikit-image
    var12 = jnp.where((w1[:-1] > 0) & (w2[1:] > 0), var12, -1.0)
    return centres[jnp.argmax(var12)] if var12.shape[0] else centres[0]


def threshold_otsu(x, nbins: int = 256, valid=None) -> jnp.ndarray:
    """Otsu threshold of the valid, finite values of ``x`` (any shape): ``x > t`` is the upper class.

    Equals ``skimage.filters.threshold_otsu(x[valid], nbins)`` for float32 input. One distinct
    value: that value. No valid value: 0. Jittable (``nbins`` static) and vmappable.
    """
    if nbins < 2:
        raise ValueError("threshold_otsu: nbins must be >= 2")
    flat, v, lo, hi = _prepare(x, valid)
    counts, centres = _histogram(flat, v, lo, hi, nbins)
    t = threshold_from_histogram(counts, centres)
    t = jnp.where(lo == hi, lo, t)
    return jnp.where(jnp.isfinite(lo), t, jnp.zeros((), flat.dtype)).astype(flat.dtype)
