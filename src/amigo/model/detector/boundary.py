"""Charge migration from first principles: pixel boundaries moved by the collected charge.

An alternative to the network of :mod:`amigo.model.detector.ramp` with two numbers (a
strength and an anisotropy) and a fixed field shape instead of 8,640 weights (``amigo
fit --detector boundary``). Photo-electrons arriving
near the boundary between two pixels are pushed away from the pixel that already holds
more charge: the boundary moves into the brighter pixel, by an amount proportional to the
component of the collected charge's field normal to it, and the electrons arriving in
the strip it sweeps go to the dimmer neighbour. Charge is conserved.

For the boundary between columns ``x`` and ``x + 1`` of row ``y``, the shift (pixels,
positive into ``x + 1``) is ``s = strength * sum_{n, m} c[n, m] (Q[y + n, x + 1 + m] -
Q[y + n, x - m])`` over ``|n| <= R`` pixels along the boundary and ``m = 0 .. R - 1``
pixels beyond it on either side, with ``c`` the normal field at the boundary's midpoint
of a point charge at each pixel's centre, a depth ``h`` below the collecting surface:
``c[n, m] = (m + 1/2) / ((m + 1/2)^2 + n^2 + h^2)^(3/2)``, normalised to one at
``n = m = 0``. The electrons moved per unit time are ``s`` times the photon rate per
pixel width at the boundary, taken from the two sub-pixel strips on either side of it.
Rows alike, with ``strength * anisotropy``. The shift is bounded smoothly at
:data:`MAX_SHIFT_PIX` (one strip; :func:`_bounded`): physical shifts are a few
hundredths of a pixel, and the edge-density estimate means nothing beyond a strip.

Why a second account: at the depth of deep programmes the network's account of a
simulated brighter-fatter effect depends on where the star falls within a pixel
(``benchmarks/bfe_phase.py``: its strength varies by +-6 % with the pixel phase and it
leaves 3-6 % of the effect's chi2), and a science star and its calibrator at
different phases then differ by more than the noise (docs/detect.md). The strength is
measured in every fit (``amigo fit``'s migration amplitude), so no training is needed.

Shapes: charge (ny, nx) electrons; sub-pixel illuminance (ny, nx, k, k) electrons.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

#: Strength (pixels of boundary shift per electron of charge difference next to the
#: boundary) this model starts from: what the shipped simulator-trained network moves in
#: the physics' pattern in F430M (docs/detector.md, "How strong the networks' charge
#: migration is": 1.4-2.1e-6). Every fit measures its own (``calibrate_migration``).
DEFAULT_STRENGTH_PIX_PER_E = 1.8e-6
#: Pixels on either side of a boundary whose charge moves it.
DEFAULT_RADIUS_PIX = 3
#: Depth of the field point below the charge, in pixels (the collecting surface is a
#: fraction of a pixel pitch from the potential wells: 18 um pixels, ~10 um).
DEFAULT_DEPTH_PIX = 0.5
#: The strength is stored in these units so the fitted number is of order one.
STRENGTH_UNIT = 1.0e-6
#: Bound of a boundary's shift (pixels): the width of the 1/3-pixel strip whose rate
#: stands for the density at the boundary.
MAX_SHIFT_PIX = 1.0 / 3.0
#: Largest field radius accepted (pixels): the field sum is unrolled over (2 R + 1) R
#: terms.
MAX_RADIUS_PIX = 8


def field_coefficients(radius_pix: int, depth_pix: float) -> np.ndarray:
    """(2 R + 1, R) weights ``c[n + R, m]``, one at ``n = m = 0`` (module docstring)."""
    n = np.arange(-radius_pix, radius_pix + 1)[:, None]
    m = np.arange(radius_pix)[None, :] + 0.5
    c = m / (m**2 + n**2 + depth_pix**2) ** 1.5
    return c / c[radius_pix, 0]


def field_sum_x(charge: Float[Array, "ny nx"], coefficients: np.ndarray) -> Array:
    """(ny, nx - 1): ``sum c[n, m] (Q[y + n, x + 1 + m] - Q[y + n, x - m])`` at the
    boundary between columns ``x`` and ``x + 1`` (no charge beyond the array)."""
    r = coefficients.shape[1]
    ny, nx = charge.shape
    q = jnp.pad(charge, r)
    out = jnp.zeros((ny, nx - 1), charge.dtype)
    for i in range(2 * r + 1):
        rows = q[i : i + ny]  # row y + n, n = i - r
        for m in range(r):
            right = rows[:, r + 1 + m : r + nx + m]
            left = rows[:, r - m : r - m + nx - 1]
            out = out + float(coefficients[i, m]) * (right - left)
    return out


def edge_rates(subpixels: Float[Array, "ny nx k k"]) -> tuple[Array, Array]:
    """Photo-electrons per pixel width at the boundaries between columns (ny, nx - 1)
    and between rows (ny - 1, nx): the mean of the two sub-pixel strips touching each
    boundary, times ``k`` (a strip is ``1 / k`` of a pixel wide)."""
    k = subpixels.shape[-1]
    last_col = subpixels[:, :-1, :, -1].sum(axis=-1)
    first_col = subpixels[:, 1:, :, 0].sum(axis=-1)
    last_row = subpixels[:-1, :, -1, :].sum(axis=-1)
    first_row = subpixels[1:, :, 0, :].sum(axis=-1)
    return 0.5 * k * (last_col + first_col), 0.5 * k * (last_row + first_row)


class BoundaryShift(eqx.Module):
    """The charge-dependent boundary shifts (module docstring).

    ``strength``: pixels per electron in units of :data:`STRENGTH_UNIT` (a scalar
    array, so that a fit or a training can move it); ``anisotropy``: the rows' strength
    over the columns'.
    """

    strength: Float[Array, ""]
    anisotropy: Float[Array, ""]
    radius_pix: int = eqx.field(static=True, default=DEFAULT_RADIUS_PIX)
    depth_pix: float = eqx.field(static=True, default=DEFAULT_DEPTH_PIX)

    @classmethod
    def create(
        cls,
        strength_pix_per_e: float = DEFAULT_STRENGTH_PIX_PER_E,
        anisotropy: float = 1.0,
        radius_pix: int = DEFAULT_RADIUS_PIX,
        depth_pix: float = DEFAULT_DEPTH_PIX,
    ) -> BoundaryShift:
        """From a strength in pixels per electron; ``ValueError`` for a field shape
        outside ``1 <= radius_pix <=`` :data:`MAX_RADIUS_PIX` and ``0 <= depth_pix``
        (finite), or a strength or anisotropy that is not finite."""
        if isinstance(radius_pix, bool) or int(radius_pix) != radius_pix:
            raise ValueError(f"radius_pix must be a whole number of pixels, not {radius_pix!r}")
        if not 1 <= int(radius_pix) <= MAX_RADIUS_PIX:
            raise ValueError(f"radius_pix must lie in 1..{MAX_RADIUS_PIX}, not {radius_pix}")
        if not (np.isfinite(depth_pix) and depth_pix >= 0):
            raise ValueError(f"depth_pix must be finite and >= 0, not {depth_pix}")
        if not (np.isfinite(strength_pix_per_e) and np.isfinite(anisotropy)):
            raise ValueError("the strength and the anisotropy must be finite")
        return cls(
            strength=jnp.asarray(strength_pix_per_e / STRENGTH_UNIT, float),
            anisotropy=jnp.asarray(anisotropy, float),
            radius_pix=int(radius_pix),
            depth_pix=float(depth_pix),
        )

    def scaled(self, scale: float) -> BoundaryShift:
        """The same shape with ``scale`` times the strength."""
        return eqx.tree_at(lambda b: b.strength, self, self.strength * scale)

    def moved(
        self,
        charge: Float[Array, "ny nx"],
        edge_x: Float[Array, "ny nxm"],
        edge_y: Float[Array, "nym nx"],
    ) -> Float[Array, "ny nx"]:
        """Electrons each pixel gains (+) or loses (-) while ``edge_x``/``edge_y`` arrive
        at the boundaries (:func:`edge_rates` of one step's sub-pixel illuminance),
        given the ``charge`` already collected. Sums to zero."""
        c = field_coefficients(self.radius_pix, self.depth_pix)
        unit = (self.strength * STRENGTH_UNIT).astype(charge.dtype)
        shift_x = _bounded(unit * field_sum_x(charge, c))
        shift_y = _bounded(unit * self.anisotropy.astype(charge.dtype) * field_sum_x(charge.T, c).T)
        flow_x = shift_x * edge_x  # from column x + 1 into column x
        flow_y = shift_y * edge_y  # from row y + 1 into row y
        zero_col = jnp.zeros((charge.shape[0], 1), charge.dtype)
        zero_row = jnp.zeros((1, charge.shape[1]), charge.dtype)
        gain = jnp.concatenate([flow_x, zero_col], 1) - jnp.concatenate([zero_col, flow_x], 1)
        gain = gain + jnp.concatenate([flow_y, zero_row], 0)
        return gain - jnp.concatenate([zero_row, flow_y], 0)


def _bounded(shift: Array) -> Array:
    """``s / (1 + (s / b)^6)^(1/6)`` with ``b =`` :data:`MAX_SHIFT_PIX`: a guard, not a
    model. Within 1e-5 of ``s`` below 0.05 pixel (the largest shifts of a 20,000 e- core
    at 1.8e-6 pix/e- are 0.03-0.05) and 0.14 % at 0.15 pixel (the strongest migration a
    fit applies to such a core), never past ``b``."""
    return shift / (1.0 + (shift / MAX_SHIFT_PIX) ** 6) ** (1.0 / 6.0)
