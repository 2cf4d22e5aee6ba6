"""The non-linear ramp model: charge accumulation with a learned brighter-fatter effect.

This is the paper's "Non-Linear Ramp Model" ("The Effective Detector Model" section): a
recurrent model that adds charge to the 80x80 pixels in a fixed number of sub-steps. At
each step a small convolutional network looks at the charge already collected and predicts,
for every pixel, a 2-D polynomial displacement of that pixel's 3x3 sub-pixel grid. The
overlap fractions of the displaced sub-pixel boxes with the pixel and its eight neighbours
form a per-pixel 3x3 kernel that moves the incoming photo-electrons: the network can only
*redistribute* charge, never create or destroy it (the kernels of each sub-pixel sum to
one), and zero charge gives exactly zero migration (no biases anywhere in the network).

Shapes and units
----------------
* illuminance: (3*ny, 3*nx) photo-electrons per integration (ramp time 0 -> 1) on the 3x
  oversampled detector grid, indexed ``[y, x]`` like the SCI arrays.
* charge: (ny, nx) electrons.
* kernels: (ny, nx, 3, 3, 3, 3) = for each pixel, for each of its 3x3 sub-pixels
  ``(sy, sx)``, the fraction of that sub-pixel's charge landing in neighbour ``(ty, tx)``
  (offsets -1, 0, +1 along y and x).

Axis order is explicit everywhere (the authors' research code transposed its kernel array
with ``.T``, which swapped pixel (r, c) with (c, r); see tests/test_ramp.py for the check).
"""

from __future__ import annotations

import functools
import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from amigo.model.detector.boundary import BoundaryShift, edge_rates

#: Offsets of the 3x3 sub-pixel centres from their pixel centre (pixels), along y and x.
SUBPIXEL_OFFSETS = np.array([-1.0, 0.0, 1.0]) / 3.0
#: Number of recurrent sub-steps over one integration (paper: a fixed number; 8).
DEFAULT_SUBSTEPS = 8
#: Charge (electrons) that maps to 1 at the network's input: keeps weights O(1).
DEFAULT_CHARGE_SCALE_E = 3.0e4
#: Largest displacement of a sub-pixel centre (pixels); tanh keeps |shift| below it so a
#: displaced sub-pixel box always stays within the 3x3 neighbourhood.
DEFAULT_MAX_SHIFT_PIX = 0.5
#: Number of polynomial terms per axis: 1, x, y, x^2, x y, y^2.
N_POLY_TERMS = 6
N_OUTPUTS = 2 * N_POLY_TERMS


def gradient_kernels() -> np.ndarray:
    """The 16 fixed spatial-gradient kernels, shape (16, 1, 3, 3) as (out, in, ky, kx).

    The charge itself, its differences to each of the 8 neighbours, first derivatives
    along x and y (Sobel), second derivatives xx, yy, xy, and the 5- and 9-point
    Laplacians. They are not trained: they present the network with the local charge
    gradients that drive charge migration (the electric field between pixels).
    """
    kernels = []
    identity = np.zeros((3, 3))
    identity[1, 1] = 1.0
    kernels.append(identity)
    for dy, dx in [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]:
        k = identity.copy()
        k[1 + dy, 1 + dx] -= 1.0  # centre minus neighbour
        kernels.append(k)
    sobel_x = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]]) / 8.0
    kernels += [sobel_x, sobel_x.T]
    kernels.append(np.array([[0, 0, 0], [1, -2, 1], [0, 0, 0]], float))  # d2/dx2
    kernels.append(np.array([[0, 1, 0], [0, -2, 0], [0, 1, 0]], float))  # d2/dy2
    kernels.append(np.array([[1, 0, -1], [0, 0, 0], [-1, 0, 1]], float) / 4.0)  # d2/dxdy
    kernels.append(np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], float))  # Laplacian
    kernels.append(np.array([[1, 1, 1], [1, -8, 1], [1, 1, 1]], float) / 3.0)
    return np.stack(kernels)[:, None].astype(np.float32)


class ChargeMigrationNetwork(eqx.Module):
    """CNN from charge to per-pixel polynomial sub-pixel displacements.

    16 fixed gradient kernels -> 3 conv layers of width 16 -> a final layer of 12 outputs;
    3x3 kernels, ReLU between layers, no biases, 'same' zero padding. Output channels
    0..5 are the x-displacement polynomial coefficients and 6..11 the y ones, in the order
    (1, x, y, x^2, x y, y^2) of the sub-pixel offsets in pixels.
    """

    layers: tuple[eqx.nn.Conv2d, ...]
    charge_scale_e: float = eqx.field(static=True)

    def __init__(
        self,
        key: jax.Array,
        width: int = 16,
        depth: int = 3,
        charge_scale_e: float = DEFAULT_CHARGE_SCALE_E,
        init_scale: float = 0.1,
    ) -> None:
        self.charge_scale_e = charge_scale_e
        channels = [gradient_kernels().shape[0]] + [width] * depth + [N_OUTPUTS]
        keys = jax.random.split(key, len(channels) - 1)
        layers = []
        for i, (c_in, c_out) in enumerate(itertools.pairwise(channels)):
            conv = eqx.nn.Conv2d(c_in, c_out, 3, padding=1, use_bias=False, key=keys[i])
            if i == len(channels) - 2:  # start close to "no migration"
                conv = eqx.tree_at(lambda c: c.weight, conv, conv.weight * init_scale)
            layers.append(conv)
        self.layers = tuple(layers)

    @property
    def n_parameters(self) -> int:
        """Number of trainable weights."""
        return sum(int(np.prod(layer.weight.shape)) for layer in self.layers)

    @eqx.filter_jit
    def __call__(self, charge_e: Float[Array, "ny nx"]) -> Float[Array, "12 ny nx"]:
        x = (charge_e / self.charge_scale_e)[None]
        # The fixed kernels are a compile-time constant, not a parameter.
        x = jax.lax.conv_general_dilated(
            x[None], jnp.asarray(gradient_kernels(), x.dtype), (1, 1), "SAME"
        )[0]
        for layer in self.layers[:-1]:
            x = jax.nn.relu(layer(x))
        return self.layers[-1](x)


def _polynomial_terms() -> np.ndarray:
    """(3, 3, 6) polynomial terms (1, x, y, x^2, x y, y^2) at each sub-pixel (sy, sx)."""
    y, x = np.meshgrid(SUBPIXEL_OFFSETS, SUBPIXEL_OFFSETS, indexing="ij")
    return np.stack([np.ones_like(x), x, y, x**2, x * y, y**2], axis=-1)


def _overlap_1d(centre: Array) -> Array:
    """Overlap of a 1/3-wide interval centred at ``centre`` with the unit intervals of
    the three target pixels at offsets -1, 0, +1; shape (..., 3), sums to 1/3."""
    lo = centre - 1.0 / 6.0
    hi = centre + 1.0 / 6.0
    targets = jnp.array([-1.0, 0.0, 1.0])
    left = jnp.maximum(lo[..., None], targets - 0.5)
    right = jnp.minimum(hi[..., None], targets + 0.5)
    return jnp.clip(right - left, 0.0, None)


@eqx.filter_jit
def migration_kernels(
    coefficients: Float[Array, "12 ny nx"], max_shift_pix: float = DEFAULT_MAX_SHIFT_PIX
) -> Float[Array, "ny nx 3 3 3 3"]:
    """Per-pixel charge-transport kernels from polynomial displacement coefficients.

    Returns ``K[py, px, sy, sx, ty, tx]``: the fraction of the charge arriving on sub-pixel
    ``(sy, sx)`` of pixel ``(py, px)`` that is collected by pixel ``(py + ty - 1,
    px + tx - 1)``. Each sub-pixel's kernel sums to one exactly (the displaced box keeps
    its area and stays inside the 3x3 neighbourhood).
    """
    terms = jnp.asarray(_polynomial_terms(), coefficients.dtype)  # (3, 3, 6)
    shift_x = jnp.einsum("stk,kyx->yxst", terms, coefficients[:N_POLY_TERMS])
    shift_y = jnp.einsum("stk,kyx->yxst", terms, coefficients[N_POLY_TERMS:])
    shift_x = max_shift_pix * jnp.tanh(shift_x / max_shift_pix)
    shift_y = max_shift_pix * jnp.tanh(shift_y / max_shift_pix)
    offsets = jnp.asarray(SUBPIXEL_OFFSETS, coefficients.dtype)
    centre_y = offsets[:, None] + shift_y  # (ny, nx, 3, 3): sub-pixel row offset
    centre_x = offsets[None, :] + shift_x
    overlap_y = _overlap_1d(centre_y)  # (ny, nx, 3, 3, 3 ty)
    overlap_x = _overlap_1d(centre_x)  # (ny, nx, 3, 3, 3 tx)
    return 9.0 * overlap_y[..., :, None] * overlap_x[..., None, :]


@eqx.filter_jit
def transport(
    subpixel_charge: Float[Array, "ny nx 3 3"], kernels: Float[Array, "ny nx 3 3 3 3"]
) -> Float[Array, "ny nx"]:
    """Move sub-pixel charge into pixels with per-pixel kernels (a dynamic convolution).

    Charge that would land outside the array is lost (the subarray edge).
    """
    ny, nx = subpixel_charge.shape[:2]
    outgoing = jnp.einsum("yxst,yxstab->yxab", subpixel_charge, kernels)  # (ny, nx, 3, 3)
    padded = jnp.pad(outgoing, ((1, 1), (1, 1), (0, 0), (0, 0)))
    total = jnp.zeros((ny, nx), subpixel_charge.dtype)
    for ty in range(3):
        for tx in range(3):
            # Charge leaving pixel (q - t + 1) towards offset t lands on pixel q.
            total = total + padded[2 - ty : 2 - ty + ny, 2 - tx : 2 - tx + nx, ty, tx]
    return total


@functools.cache
def read_weights(n_substeps: int, ngroups: int) -> np.ndarray:
    """(ngroups, n_substeps + 1) weights taking the charge at the sub-steps (times
    ``k / n_substeps`` of the ramp, k = 0..n_substeps) to the charge at the group reads
    (times ``(g + 1) / ngroups``), by a not-a-knot cubic spline through the sub-steps.

    A spline is linear in the values it interpolates, so it is this fixed matrix: computed
    once in NumPy (the spline of the identity), it keeps the spline's solve out of every
    compiled model and gradient. Written out here rather than taken from
    ``scipy.interpolate.CubicSpline`` (which it equals to rounding, tests/test_ramp.py):
    importing that module cost every fitting process 0.3 s on a CPU and 1.2 s on a GPU
    machine (docs/performance.md).
    """
    n = n_substeps
    read_times = np.arange(1, ngroups + 1) / ngroups
    identity = np.eye(n + 1)
    if n < 3:  # 2 or 3 knots: not-a-knot is the line or the parabola through them
        powers = np.linspace(0.0, 1.0, n + 1)[:, None] ** np.arange(n + 1)
        coefficients = np.linalg.solve(powers, identity)  # (degree + 1, knots)
        weights = (read_times[:, None] ** np.arange(n + 1)) @ coefficients
    else:
        weights = _not_a_knot_weights(n, read_times)
    weights.setflags(write=False)
    return weights


def _not_a_knot_weights(n: int, read_times: np.ndarray) -> np.ndarray:
    """(reads, n + 1) values at ``read_times`` in [0, 1] of the not-a-knot cubic spline
    through ``n + 1 >= 4`` equally spaced knots, per unit value at each knot.

    Unknowns: the second derivatives ``m_k`` at the knots. Interior knots: continuity of
    the first derivative, ``m_(k-1) + 4 m_k + m_(k+1) = 6 (y_(k-1) - 2 y_k + y_(k+1)) /
    h^2``; the ends: the third derivative continuous across the second and the
    second-to-last knots (``m_0 - 2 m_1 + m_2 = 0`` and its mirror).
    """
    h = 1.0 / n
    system = np.zeros((n + 1, n + 1))
    right = np.zeros((n + 1, n + 1))  # right-hand sides, per unit knot value
    for k in range(1, n):
        system[k, k - 1 : k + 2] = [1.0, 4.0, 1.0]
        right[k, k - 1 : k + 2] = np.array([1.0, -2.0, 1.0]) * 6.0 / h**2
    system[0, :3] = [1.0, -2.0, 1.0]
    system[n, n - 2 :] = [1.0, -2.0, 1.0]
    m = np.linalg.solve(system, right)  # (knots, unit values): second derivatives
    interval = np.clip(np.floor(read_times / h).astype(int), 0, n - 1)
    left = interval * h
    a, b = (left + h - read_times)[:, None], (read_times - left)[:, None]  # to each end
    y = np.eye(n + 1)
    lo, hi = interval, interval + 1
    return (
        m[lo] * a**3 / (6 * h)
        + m[hi] * b**3 / (6 * h)
        + (y[lo] / h - m[lo] * h / 6) * a
        + (y[hi] / h - m[hi] * h / 6) * b
    )


def to_subpixels(image: Float[Array, "ny3 nx3"]) -> Float[Array, "ny nx 3 3"]:
    """Reshape a 3x oversampled image to (ny, nx, sy, sx) sub-pixel blocks."""
    ny, nx = image.shape[0] // 3, image.shape[1] // 3
    return image.reshape(ny, 3, nx, 3).transpose(0, 2, 1, 3)


class IntraPixelResponse(eqx.Module):
    """Quadratic sensitivity across a pixel, the same for every pixel.

    ``r(x, y) = 1 + c . (x, y, x^2, x y, y^2)`` at the sub-pixel offsets, normalised to a
    mean of one over the 9 sub-pixels so that the flat field keeps the meaning of a pixel's
    total sensitivity.
    """

    coefficients: Float[Array, 5]

    def __init__(self, coefficients: Array | None = None) -> None:
        self.coefficients = jnp.zeros(5) if coefficients is None else jnp.asarray(coefficients)

    def __call__(self) -> Float[Array, "3 3"]:
        terms = jnp.asarray(_polynomial_terms()[..., 1:], self.coefficients.dtype)
        response = 1.0 + terms @ self.coefficients
        return response / response.mean()


class RampModel(eqx.Module):
    """Recurrent charge accumulation over one integration, with or without migration.

    Attributes
    ----------
    network
        :class:`ChargeMigrationNetwork`, the physical
        :class:`~amigo.model.detector.boundary.BoundaryShift` (``--detector boundary``),
        or ``None`` for linear charge accumulation (the ``--detector linear``
        comparison).
    flat
        (ny, nx) inter-pixel sensitivity (flat field), mean ~1.
    intra_pixel
        :class:`IntraPixelResponse`.
    n_substeps
        Recurrent steps per integration.
    max_shift_pix
        Bound of the sub-pixel displacements.
    """

    network: ChargeMigrationNetwork | BoundaryShift | None
    flat: Float[Array, "ny nx"]
    intra_pixel: IntraPixelResponse
    n_substeps: int = eqx.field(static=True, default=DEFAULT_SUBSTEPS)
    max_shift_pix: float = eqx.field(static=True, default=DEFAULT_MAX_SHIFT_PIX)

    @classmethod
    def create(
        cls,
        key: jax.Array | None = None,
        shape: tuple[int, int] = (80, 80),
        n_substeps: int = DEFAULT_SUBSTEPS,
        linear: bool = False,
    ) -> RampModel:
        """A fresh model: unit flat, flat intra-pixel response, new network weights."""
        network = None
        if not linear:
            network = ChargeMigrationNetwork(jax.random.PRNGKey(0) if key is None else key)
        return cls(
            network=network,
            flat=jnp.ones(shape),
            intra_pixel=IntraPixelResponse(),
            n_substeps=n_substeps,
        )

    @eqx.filter_jit
    def charge_states(self, illuminance_e: Float[Array, "ny3 nx3"]) -> Float[Array, "n ny nx"]:
        """Charge after each sub-step, including the empty start: (n_substeps + 1, ny, nx),
        in the illuminance's precision (constants promoted to float64 when x64 is on must
        not change the type of the recurrent state)."""
        dtype = illuminance_e.dtype
        step = to_subpixels(illuminance_e) * self.intra_pixel()[None, None] / self.n_substeps
        step = step.astype(dtype)
        ny, nx = step.shape[:2]
        # The physical account's photon rates at the boundaries: the same every step.
        edges = edge_rates(step) if isinstance(self.network, BoundaryShift) else None

        def advance(charge: Array, _: None) -> tuple[Array, Array]:
            if self.network is None:
                collected = step.sum(axis=(2, 3))
            elif isinstance(self.network, BoundaryShift):
                assert edges is not None
                collected = step.sum(axis=(2, 3)) + self.network.moved(charge, *edges)
            else:
                kernels = migration_kernels(self.network(charge), self.max_shift_pix)
                collected = transport(step, kernels)
            charge = charge + (self.flat * collected).astype(dtype)
            return charge, charge

        start = jnp.zeros((ny, nx), dtype)
        _, states = jax.lax.scan(advance, start, None, length=self.n_substeps)
        return jnp.concatenate([start[None], states])

    @eqx.filter_jit
    def __call__(
        self, illuminance_e: Float[Array, "ny3 nx3"], ngroups: int
    ) -> Float[Array, "ngroups ny nx"]:
        """Charge (electrons) at the group reads, times (k + 1) / ngroups of the ramp."""
        states = self.charge_states(illuminance_e)
        weights = jnp.asarray(read_weights(self.n_substeps, ngroups), states.dtype)
        return jnp.tensordot(weights, states, 1)
