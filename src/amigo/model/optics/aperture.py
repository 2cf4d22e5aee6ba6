"""The non-redundant mask: pupil grid, soft-edged hexagonal holes, distortions, Zernikes.

Conventions
-----------
* Pupil frame: metres, ``+x``/``+y`` along detector ``+x``/``+y`` (see
  :mod:`amigo.niriss`). Arrays are indexed ``[y, x]``.
* Holes are regular hexagons with two flat edges parallel to ``x`` ("flat-top": flats at
  ``y = +-f2f/2``, vertices on the ``x`` axis), the orientation of the JWST segments
  whose centres the holes sit on (columns 1.143 m apart, rows 1.32 m = one flat-to-flat).
* Soft edges: the transmission is a linear ramp of the signed distance to the hexagon
  edge, ``clip(1/2 - d / (s * pixel), 0, 1)``, with ``s`` = ``softening_px`` pupil pixels
  (1 = an area-weighted edge to first order). It makes the pupil a smooth function of the
  hole geometry, so gradients reach positions, sizes and distortions.
* Distortions are 2-D polynomials without constant terms, applied to the coordinates on
  which the holes are drawn: a global one on the whole pupil (normalised by the pupil
  radius; it moves and shears the holes together, but cannot shift the mask as a whole),
  and one per hole on the hole's own coordinates (normalised by the hole circumradius; it
  distorts each hexagon's shape).
* Zernikes: Noll-ordered, unit-rms on a disc of ``zernike_radius_factor`` times the hole
  circumradius centred on each hole's nominal centre (the wavefront belongs to the
  telescope, so it does not follow the mask distortions), and extended (same
  polynomials) to half the closest hole spacing.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Protocol, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax import lax
from jaxtyping import Array, Float

from amigo import niriss

#: Unit normals of the three pairs of edges of a flat-top hexagon (30, 90, 150 deg).
_HEX_NORMAL_ANGLES_RAD = np.deg2rad([30.0, 90.0, 150.0])


def polynomial_powers(order: int) -> np.ndarray:
    """(n_terms, 2) exponents ``(i, j)`` of ``x**i * y**j`` with ``1 <= i + j <= order``.

    Ordered by total degree, then by decreasing power of ``x``: for order 2,
    ``x, y, x^2, xy, y^2``. The constant term is excluded on purpose (see module notes).
    """
    return np.array([(d - j, j) for d in range(1, order + 1) for j in range(d + 1)], dtype=int)


def n_polynomial_terms(order: int) -> int:
    """Number of terms of :func:`polynomial_powers` (``order * (order + 3) / 2``)."""
    return order * (order + 3) // 2


def polynomial_displacement(
    x: Array, y: Array, coefficients: Float[Array, "2 k"], powers: np.ndarray
) -> tuple[Array, Array]:
    """Displacement ``(dx, dy) = sum_k c[:, k] x**i_k y**j_k`` (same shape as ``x``)."""
    # Powers by repeated products: ``x**0`` would differentiate to 0 * x**-1 = nan at 0.
    top = int(np.max(powers))
    xp, yp = [jnp.ones_like(x), x], [jnp.ones_like(y), y]
    for _ in range(2, top + 1):
        xp.append(xp[-1] * x)
        yp.append(yp[-1] * y)
    terms = jnp.stack([xp[i] * yp[j] for i, j in powers])  # (k, ...)
    return jnp.tensordot(coefficients[0], terms, 1), jnp.tensordot(coefficients[1], terms, 1)


def soft_hexagon(x: Array, y: Array, flat_to_flat_m: Array, edge_m: float) -> Array:
    """Soft-edged flat-top hexagon centred on the origin, values in [0, 1].

    ``edge_m`` is the width of the linear ramp across the edge (metres). The ramp's
    level sets are hexagons of flat-to-flat ``w + 2 t`` for ``t`` across the ramp, whose
    mean area exceeds the hexagon's by the fraction ``edge^2 / (3 w^2)``; the hexagon is
    drawn that much smaller so that the soft hole has the area of the true one.
    """
    half = 0.5 * jnp.sqrt(flat_to_flat_m**2 - edge_m**2 / 3.0)
    # Pairwise maxima, not a max-reduction: the reduction's gradient divides by the
    # number of entries equal to the maximum, which XLA's fused (FMA) recomputation can
    # make zero, giving nan under jit.
    a, b, c = (jnp.abs(np.cos(t) * x + np.sin(t) * y) for t in _HEX_NORMAL_ANGLES_RAD)
    distance = jnp.maximum(jnp.maximum(a, b), c)
    return jnp.clip(0.5 - (distance - half) / edge_m, 0.0, 1.0)


class PupilGrid(eqx.Module):
    """Pixel centres of the pupil plane, cropped to the mask.

    The sampling is ``pixel_m = diameter_m / npix`` (``npix`` pixels across the JWST
    pupil diameter), but only the rows and columns that can hold a hole (the mask's
    bounding box plus a margin for distortions) are kept: the propagation cost scales
    with the number of pupil pixels, and the rest of the pupil is opaque.

    Attributes
    ----------
    x_m, y_m
        (nx,), (ny,) coordinates of the pixel centres (metres, pupil frame), on the
        lattice ``(k + 1/2) * pixel_m`` of the full pupil grid.
    pixel_m
        Pixel pitch (metres).
    """

    x_m: Float[Array, " nx"]
    y_m: Float[Array, " ny"]
    pixel_m: float = eqx.field(static=True)

    @classmethod
    def for_mask(
        cls,
        npix: int = 256,
        diameter_m: float = niriss.PUPIL_DIAMETER_M,
        centres_m: np.ndarray = niriss.HOLE_CENTRES_M,
        flat_to_flat_m: float = niriss.HOLE_FLAT_TO_FLAT_M,
        margin_m: float = 0.1,
    ) -> PupilGrid:
        """Grid of pitch ``diameter_m / npix`` covering the holes plus ``margin_m``."""
        pixel = diameter_m / npix
        centres = np.asarray(centres_m)
        # Half extents of a flat-top hexagon: circumradius along x, half flat-to-flat in y.
        half = np.array([flat_to_flat_m / np.sqrt(3), 0.5 * flat_to_flat_m]) + margin_m
        lo, hi = centres.min(axis=0) - half, centres.max(axis=0) + half
        # Pixel centres on the lattice (k + 1/2) * pixel (symmetric about zero when full).
        first = np.floor(lo / pixel - 0.5).astype(int)
        last = np.ceil(hi / pixel - 0.5).astype(int)
        x, y = ((np.arange(a, b + 1) + 0.5) * pixel for a, b in zip(first, last, strict=True))
        return cls(x_m=jnp.asarray(x), y_m=jnp.asarray(y), pixel_m=float(pixel))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.y_m.shape[0], self.x_m.shape[0])

    def coordinates(self) -> tuple[Float[Array, "ny nx"], Float[Array, "ny nx"]]:
        """``(x, y)`` coordinate arrays, each (ny, nx)."""
        y, x = jnp.meshgrid(self.y_m, self.x_m, indexing="ij")
        return x, y


def noll_indices(j: int) -> tuple[int, int]:
    """Radial and azimuthal orders ``(n, m)`` of Noll's Zernike ``j >= 1`` (Noll 1976).

    Row ``n`` holds ``n + 1`` modes, ordered by ``|m|`` (each ``m != 0`` twice); an even
    ``j`` is the cosine mode (``m > 0``), an odd one the sine (``m < 0``): j = 2, 3 are
    tip and tilt (n = 1, m = +-1), j = 4 defocus, j = 5, 6 astigmatism (m = -2, +2).
    """
    if j < 1:
        raise ValueError(f"Noll index {j} < 1")
    n, first = 0, 1
    while first + n + 1 <= j:  # row n covers first .. first + n
        first += n + 1
        n += 1
    orders = [abs_m for abs_m in range(n % 2, n + 1, 2) for _ in range(1 if abs_m == 0 else 2)]
    abs_m = orders[j - first]
    return n, (abs_m if j % 2 == 0 else -abs_m) if abs_m else 0


@functools.cache
def _zernike_factors(j: int) -> tuple[int, int, np.ndarray, np.ndarray]:
    """``(n, m, c, k)`` of Noll mode ``j``: the radial polynomial is
    ``R(rho) = sum_i c_i rho^(n - 2 k_i)`` with
    ``c_k = (-1)^k (n - k)! / (k! ((n + |m|)/2 - k)! ((n - |m|)/2 - k)!)``, the
    un-normalised form that :func:`_radial` evaluates (the sqrt(n + 1) normalisation is
    in :func:`_azimuthal`). Plain integers: computed this way once per mode it costs
    microseconds, where factorials traced by JAX took seconds per mode."""
    n, m = noll_indices(j)
    a = abs(m)
    k = np.arange((n - a) // 2 + 1)
    c = np.array(
        [
            (-1) ** int(i)
            * math.factorial(n - int(i))
            / (
                math.factorial(int(i))
                * math.factorial((n + a) // 2 - int(i))
                * math.factorial((n - a) // 2 - int(i))
            )
            for i in k
        ]
    )
    return n, m, c, k.astype(float)


def _radial(rho: Array, n: int, c: np.ndarray, k: np.ndarray) -> Array:
    """``R(rho) = sum_i c_i rho^(n - 2 k_i)`` on a (ny, nx) grid of ``rho`` (unit: the
    normalisation radius)."""
    powers = lax.pow(rho[:, :, None], (abs(n) - 2 * k)[None, None, :])
    return (c * powers).sum(axis=2)


def _azimuthal(theta: Array, n: int, m: int) -> Array:
    """The angular factor with the unit-rms normalisation on the disc: ``sqrt(n + 1)``
    times ``1`` (``m = 0``), ``sqrt(2) cos(m theta)`` (``m > 0``) or ``sqrt(2)
    sin(|m| theta)`` (``m < 0``): Noll (1976)."""
    norm = math.sqrt(n + 1) * (math.sqrt(2.0) if m != 0 else 1.0)
    trig = jnp.cos if m >= 0 else jnp.sin
    return norm * trig(abs(m) * theta)


def zernike_basis(
    grid: PupilGrid,
    centres_m: Float[Array, "h 2"] | np.ndarray,
    radius_m: Array | float,
    n_modes: int,
    support_m: Array | float | None = None,
) -> Float[Array, "h j ny nx"]:
    """Noll Zernikes ``1..n_modes`` about each hole centre, unit rms on a disc of ``radius_m``.

    The polynomials are evaluated out to ``support_m`` (default ``radius_m``) and are zero
    beyond: a support a little larger than the normalisation disc keeps the wavefront
    defined wherever the sharpened hole amplitude is not zero.
    """
    x, y = grid.coordinates()
    factors = [_zernike_factors(j) for j in range(1, n_modes + 1)]
    support = radius_m if support_m is None else support_m

    def one_hole(centre):
        dx, dy = jnp.stack([x - centre[0], y - centre[1]]) / radius_m
        rho, theta = jnp.hypot(dx, dy), jnp.arctan2(dy, dx)
        inside = rho * radius_m <= support
        return jnp.stack(
            [
                inside
                * _radial(rho, n, c.astype(rho.dtype), k.astype(rho.dtype))
                * _azimuthal(theta, n, m)
                for n, m, c, k in factors
            ]
        )

    return jax.vmap(one_hole)(jnp.asarray(centres_m))


@dataclasses.dataclass(frozen=True)
class HoleWindows:
    """One square window of the pupil grid per hole, holding the support of that hole's
    Zernikes (static, hashable: a compiled program's shapes).

    A Zernike coefficient of one hole changes the pupil field only where that hole's
    polynomials are non-zero, a disc of half the closest hole spacing, so its tangent
    needs a transform of that window alone (:meth:`amigo.model.optics.NRMOptics.
    wavefront_psf_tangents`): 43 of the 220 x 222 rows and columns of the 256-pixel
    pupil's grid.

    Attributes
    ----------
    size
        Pupil pixels per side of every window (the same for all holes, so that one
        compiled step serves them all).
    origins
        ``(row, column)`` of each window's first pixel on the pupil grid, one per hole.
    """

    size: int
    origins: tuple[tuple[int, int], ...]


def hole_windows(basis: npt.ArrayLike) -> HoleWindows:
    """The smallest common :class:`HoleWindows` holding the support of each hole's
    Zernikes, from a concrete basis (h, j, ny, nx) (host arrays, not traced).

    Each window is centred on its hole's support and moved inside the grid where it
    would cross an edge; what lies in a window besides its own hole's support (other
    holes' pixels) has a zero tangent, so a window may hold anything else.
    """
    support = np.any(np.asarray(basis) != 0, axis=1)  # (h, ny, nx)
    ny, nx = support.shape[1:]
    boxes = []
    for mask in support:
        rows, cols = np.nonzero(np.any(mask, axis=1))[0], np.nonzero(np.any(mask, axis=0))[0]
        if rows.size == 0:  # no support: any window (its tangents are zero)
            rows, cols = np.array([0]), np.array([0])
        boxes.append((rows[0], rows[-1] + 1, cols[0], cols[-1] + 1))
    size = max(max(r1 - r0, c1 - c0) for r0, r1, c0, c1 in boxes)
    size = min(size, ny, nx)

    def origin(lo: int, hi: int, n: int) -> int:
        return int(np.clip(lo - (size - (hi - lo)) // 2, 0, n - size))

    origins = tuple((origin(r0, r1, ny), origin(c0, c1, nx)) for r0, r1, c0, c1 in boxes)
    return HoleWindows(int(size), origins)


class Aperture(eqx.Module):
    """Dynamic (fittable) mask geometry, rendered on every call.

    Attributes
    ----------
    centres_m
        (7, 2) nominal hole centres ``(x, y)``, metres (default
        :data:`amigo.niriss.HOLE_CENTRES_M`). Fitting them frees the global shift of
        the mask, which the intensity barely constrains: prefer the global distortion.
    flat_to_flat_m
        Hole size (flat-to-flat, metres; default 0.80).
    global_distortion
        (2, k) coefficients of the global polynomial (dimensionless: displacement in
        units of the pupil radius at unit normalised coordinate); ``k`` from
        :func:`n_polynomial_terms`.
    hole_distortion
        (7, 2, k') per-hole polynomial coefficients (units of the hole circumradius).
    """

    centres_m: Float[Array, "7 2"]
    flat_to_flat_m: Float[Array, ""]
    global_distortion: Float[Array, "2 k"]
    hole_distortion: Float[Array, "7 2 kh"]
    global_scale_m: float = eqx.field(static=True, default=0.5 * niriss.PUPIL_DIAMETER_M)

    @classmethod
    def nominal(
        cls,
        flat_to_flat_m: float = niriss.HOLE_FLAT_TO_FLAT_M,
        global_order: int = 3,
        hole_order: int = 2,
        centres_m: np.ndarray = niriss.HOLE_CENTRES_M,
    ) -> Aperture:
        """Undistorted mask with the given polynomial orders (all coefficients zero)."""
        return cls(
            centres_m=jnp.asarray(np.asarray(centres_m, dtype=float)),
            flat_to_flat_m=jnp.asarray(float(flat_to_flat_m)),
            global_distortion=jnp.zeros((2, n_polynomial_terms(global_order))),
            hole_distortion=jnp.zeros((niriss.N_HOLES, 2, n_polynomial_terms(hole_order))),
        )

    @property
    def circumradius_m(self) -> Array:
        return self.flat_to_flat_m / np.sqrt(3.0)

    def _order(self, n_terms: int) -> int:
        order = round((-3 + np.sqrt(9 + 8 * n_terms)) / 2)
        if n_polynomial_terms(order) != n_terms:
            raise ValueError(f"{n_terms} is not a number of polynomial terms")
        return order

    def hole_transmissions(
        self, grid: PupilGrid, softening_px: float = 1.0, supersample: int = 1
    ) -> Float[Array, "7 ny nx"]:
        """(7, ny, nx) amplitude transmission of each hole (soft edges, values in [0, 1]).

        With ``supersample`` > 1 each pixel is the mean of ``supersample^2`` sub-samples
        (soft edges of ``softening_px`` sub-sample widths): closer to a pixel average.
        """
        offsets = (np.arange(supersample) - 0.5 * (supersample - 1)) / supersample
        edge_m = softening_px * grid.pixel_m / supersample
        total: float | Array = 0.0
        for oy in offsets:
            for ox in offsets:
                total = total + self._draw(grid, ox * grid.pixel_m, oy * grid.pixel_m, edge_m)
        return cast(Array, total) / supersample**2  # an Array: supersample >= 1

    def _draw(self, grid: PupilGrid, dx_m: float, dy_m: float, edge_m: float) -> Array:
        x, y = grid.coordinates()
        x, y = x + dx_m, y + dy_m
        scale = self.global_scale_m
        gx, gy = polynomial_displacement(
            x / scale,
            y / scale,
            self.global_distortion,
            polynomial_powers(self._order(self.global_distortion.shape[-1])),
        )
        x, y = x + scale * gx, y + scale * gy
        rc = self.circumradius_m
        powers = polynomial_powers(self._order(self.hole_distortion.shape[-1]))

        def one_hole(centre, coefficients):
            qx, qy = x - centre[0], y - centre[1]
            hx, hy = polynomial_displacement(qx / rc, qy / rc, coefficients, powers)
            return soft_hexagon(qx + rc * hx, qy + rc * hy, self.flat_to_flat_m, edge_m)

        # vmap, not a Python loop over holes: one copy of the graph, not seven, to compile.
        return jax.vmap(one_hole)(self.centres_m, self.hole_distortion)

    def zernike_basis(self, grid: PupilGrid, n_modes: int, radius_factor: float) -> Array:
        """(7, n_modes, ny, nx) per-hole Zernike basis (see module notes).

        Normalised on ``radius_factor`` times the hole circumradius, supported out to
        half the closest hole spacing (0.66 m), so the discs never overlap.
        """
        centres = self.centres_m
        gaps = jnp.linalg.norm(centres[:, None] - centres[None, :], axis=-1)
        gaps = gaps + jnp.eye(centres.shape[0]) * 1e9
        support = 0.5 * jax.lax.stop_gradient(jnp.min(gaps))
        return zernike_basis(grid, centres, radius_factor * self.circumradius_m, n_modes, support)


class MaskModel(Protocol):
    """What the optics reads of a mask: :class:`Aperture`, :class:`StaticAperture` and
    :class:`amigo.model.base.MovableHoles` have these two methods."""

    def hole_transmissions(
        self, grid: PupilGrid, softening_px: float = 1.0, supersample: int = 1
    ) -> Array: ...

    def zernike_basis(self, grid: PupilGrid, n_modes: int, radius_factor: float) -> Array: ...


@eqx.filter_jit
def _render(
    aperture: MaskModel,
    grid: PupilGrid,
    n_modes: int,
    radius_factor: float,
    softening_px: float,
    supersample: int,
) -> tuple[Array, Array]:
    """Hole transmissions and Zernike basis of ``aperture``, compiled as one program
    (evaluated op by op they took two minutes on a 2-core CPU, for a 64-pixel pupil)."""
    return (
        aperture.hole_transmissions(grid, softening_px, supersample),
        aperture.zernike_basis(grid, n_modes, radius_factor),
    )


class StaticAperture(eqx.Module):
    """Precomputed mask (the fast path): hole transmissions and Zernike basis as arrays.

    It has no geometric parameters, so nothing of the mask can be fitted through it
    (gradients cannot silently vanish); build it from an :class:`Aperture` with
    :meth:`from_aperture` and go back to the dynamic path to fit the geometry.
    """

    holes: Float[Array, "7 ny nx"]
    basis: Float[Array, "7 j ny nx"]

    @classmethod
    def from_aperture(
        cls,
        aperture: MaskModel,
        grid: PupilGrid,
        n_modes: int,
        radius_factor: float,
        softening_px: float,
        supersample: int = 1,
    ) -> StaticAperture:
        holes, basis = _render(aperture, grid, n_modes, radius_factor, softening_px, supersample)
        return cls(holes=holes, basis=basis)

    def hole_transmissions(
        self, grid: PupilGrid, softening_px: float = 1.0, supersample: int = 1
    ) -> Array:
        del grid, softening_px, supersample  # fixed at construction
        return self.holes

    def zernike_basis(self, grid: PupilGrid, n_modes: int, radius_factor: float) -> Array:
        del grid, radius_factor
        if n_modes != self.basis.shape[1]:
            raise ValueError(f"static basis has {self.basis.shape[1]} modes, not {n_modes}")
        return self.basis
