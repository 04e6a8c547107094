"""processing.angle_kernels: the wrapped phase of a complex product, as every frame's quality mask takes it."""

import numpy as np
import pytest


def test_the_angle_of_a_product_is_the_exact_angle_to_float32():
    """angle_of_product(a, b) against the angle of the product in complex128: within 1.5e-7 rad (half a
    float32 unit at pi, plus the arctangent's 6.3e-9) on random complex64 signals of every octant and
    magnitude, on the axes and diagonals (signs of zero included: -pi below the negative real axis, as
    NumPy gives), NaN for NaN; NumPy's own complex64 angle is the yardstick it must not be worse than."""
    from processing.angle_kernels import angle_of_product

    rng = np.random.default_rng(3)
    shape = (2, 97, 131)
    scale = 10.0 ** rng.uniform(-3, 4, shape)
    a = ((rng.normal(size=shape) + 1j * rng.normal(size=shape)) * scale).astype(np.complex64)
    b = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(np.complex64)
    got = angle_of_product(a, b)
    assert got.dtype == np.float32 and got.shape == shape
    exact = np.angle(a.astype(np.complex128) * b.astype(np.complex128))
    error = np.abs(np.angle(np.exp(1j * (got.astype(np.float64) - exact))))
    numpy_error = np.abs(np.angle(np.exp(1j * (np.angle(a * b).astype(np.float64) - exact))))
    assert error.max() < 1.5e-7 and error.max() <= numpy_error.max()

    unit = np.ones(8, np.complex64)
    z = np.array([1, 1 + 1j, 1j, -1 + 1j, -1, -1 - 1j, -1j, 1 - 1j], np.complex64)
    assert np.allclose(angle_of_product(z, unit), np.angle(z.astype(np.complex128)), atol=1.5e-7, rtol=0)
    special = np.array([complex(-1.0, -0.0), complex(-1.0, 0.0), 0, complex(np.nan, 1.0)], np.complex64)
    out = angle_of_product(special, np.ones(4, np.complex64))
    assert out[0] == np.float32(-np.pi) and out[1] == np.float32(np.pi) and out[2] == 0 and np.isnan(out[3])
    with pytest.raises(ValueError, match="differ"):
        angle_of_product(a, b[:1])
