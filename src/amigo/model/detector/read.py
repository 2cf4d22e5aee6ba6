"""The read electronics: dark current, IPC, non-linear gain, gain and 1/f noise.

The paper's "Electronics & Read model": the last step from collected charge to the numbers
the detector writes. Applied to the charge at every group read, in this order:

1. dark current, added per group: ``q_k += (k + 1) * dark_e_per_group``;
2. inter-pixel capacitance: a 5x5 convolution of each group read with a static kernel;
3. per-pixel quadratic non-linearity: ``q -> q + nl * q**2`` (``nl`` per pixel, 1/e-;
   negative for the H2RG's sub-linear response);
4. gain: ``DN = q / gain``;
5. optionally 1/f noise: a low-order polynomial along each column, per group (DN);
6. optionally a fixed offset of each pixel in each group read (DN, ``group_offsets_dn``):
   behind the STScI pipeline (level-2 images), what its dark subtraction left in the ramp
   (:mod:`amigo.model.detector.dark_residual`).

Slopes are the group differences of the result: (ngroups - 1, ny, nx) DN per group.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from amigo import niriss


def default_ipc_kernel() -> np.ndarray:
    """The default 5x5 IPC kernel, indexed ``[dy + 2, dx + 2]``, summing to one.

    Source: CRDS NIRISS IPC reference values as recorded in the AMIGO research notes:
    centre 0.980177; left/right 4.710e-3; up (+y) 3.980e-3, down (-y) 5.028e-3;
    diagonals 3.085e-4; outer ring ~1e-5..3e-5 (2e-5 used); outer corners -6.5e-6. The
    centre is then adjusted (by < 2e-4) so the kernel conserves charge exactly.
    """
    kernel = np.full((5, 5), 2.0e-5)
    kernel[[0, 0, 4, 4], [0, 4, 0, 4]] = -6.5e-6
    kernel[1:4, 1:4] = 3.085e-4
    kernel[2, 1] = kernel[2, 3] = 4.710e-3
    kernel[3, 2] = 3.980e-3  # up: +y, the next row
    kernel[1, 2] = 5.028e-3  # down: -y
    kernel[2, 2] = 0.0
    kernel[2, 2] = 1.0 - kernel.sum()
    return kernel


@eqx.filter_jit
def convolve_ipc(frames: Float[Array, "... ny nx"], kernel: Float[Array, "5 5"]) -> Array:
    """Convolve each frame with the IPC kernel (zero padding at the subarray edges).

    ``out[y, x] = sum_{dy, dx} kernel[dy + 2, dx + 2] * in[y - dy, x - dx]``: the charge of
    pixel (y, x) couples a fraction ``kernel[dy + 2, dx + 2]`` into pixel (y + dy, x + dx).
    """
    ny, nx = frames.shape[-2:]
    kernel = jnp.asarray(kernel, frames.dtype)
    widths = [(0, 0)] * (frames.ndim - 2) + [(2, 2), (2, 2)]
    padded = jnp.pad(frames, widths)
    # Twenty-five shifted copies, weighted and summed (XLA fuses them into one pass):
    # the same sums as jax.lax.conv_general_dilated, which on a CPU is built for many
    # channels and took 0.59 ms per 80 x 80 image against 0.014 ms (a batch of 64). IPC
    # is applied to every column of every Jacobian: the float32 local Jacobian of an
    # F480M exposure (1093 columns, 2-core CPU) 2.59 -> 2.01 s.
    out = jnp.zeros_like(frames)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            shifted = padded[..., 2 - dy : 2 - dy + ny, 2 - dx : 2 - dx + nx]
            out = out + kernel[dy + 2, dx + 2] * shifted
    return out


class ReadModel(eqx.Module):
    """Charge at the group reads (electrons) -> raw ramp (DN).

    Attributes
    ----------
    dark_e_per_group
        (ny, nx) dark current per group time (electrons) of each pixel; a 0-d value
        applies to all pixels.
    ipc_kernel
        (5, 5) IPC kernel (see :func:`default_ipc_kernel`).
    nonlinearity
        (ny, nx) quadratic coefficient per pixel (1/electron).
    gain_e_per_dn
        Electrons per DN.
    one_over_f
        ``None``, or (ngroups, nx, order + 1) polynomial coefficients (DN) of a per-column,
        per-group offset in the normalised row coordinate.
    group_offsets_dn
        ``None``, or (G, ny, nx) offsets (DN) added to group reads 0 .. G-1 of every
        integration (later reads get none): the same in every exposure processed with one
        dark reference file (see :mod:`amigo.model.detector.dark_residual`).
    group_offsets_chol_dn
        ``None``, or (G, G, ny, nx) lower Cholesky factor (DN) of the offsets' posterior
        covariance per pixel: not part of the image, the uncertainty it leaves
        (:func:`amigo.model.detector.dark_residual.offset_variance`).
    superbias_dn, superbias_var_dn2
        ``None``, or (ny, nx) each: the detector's mean reset level per pixel (DN) and the
        variance of that estimate (DN^2), measured on dark exposures at training
        (:mod:`amigo.model.detector.reset`). Not part of the modelled reads (which are above
        the reset level): a fit of calslope data subtracts it from the first read so the
        first group's photons enter the likelihood.
    """

    dark_e_per_group: Float[Array, "ny nx"] | Float[Array, ""]
    ipc_kernel: Float[Array, "5 5"]
    nonlinearity: Float[Array, "ny nx"]
    gain_e_per_dn: float = eqx.field(static=True, default=niriss.GAIN_E_PER_DN)
    one_over_f: Float[Array, "ng nx k"] | None = None
    group_offsets_dn: Float[Array, "G ny nx"] | None = None
    group_offsets_chol_dn: Float[Array, "G G ny nx"] | None = None
    superbias_dn: Float[Array, "ny nx"] | None = None
    superbias_var_dn2: Float[Array, "ny nx"] | None = None

    @classmethod
    def create(cls, shape: tuple[int, int] = (80, 80)) -> ReadModel:
        """Defaults: no dark, the default IPC kernel, linear response, the NIRISS gain."""
        return cls(
            dark_e_per_group=jnp.zeros(shape),
            ipc_kernel=jnp.asarray(default_ipc_kernel()),
            nonlinearity=jnp.zeros(shape),
        )

    @eqx.filter_jit
    def __call__(self, charge_e: Float[Array, "ng ny nx"]) -> Float[Array, "ng ny nx"]:
        ngroups = charge_e.shape[0]
        reads = jnp.arange(1, ngroups + 1, dtype=charge_e.dtype)[:, None, None]
        q = charge_e + reads * self.dark_e_per_group
        q = convolve_ipc(q, self.ipc_kernel)
        q = q + self.nonlinearity * q**2
        dn = q / self.gain_e_per_dn
        if self.one_over_f is not None:
            ny = charge_e.shape[1]
            rows = jnp.linspace(-1.0, 1.0, ny)
            powers = rows[:, None] ** jnp.arange(self.one_over_f.shape[-1])  # (ny, k)
            dn = dn + jnp.einsum("yk,gxk->gyx", powers, self.one_over_f)
        if self.group_offsets_dn is not None:
            dn = dn + group_offsets(self.group_offsets_dn, ngroups).astype(dn.dtype)
        return dn


def group_offsets(offsets_dn: Float[Array, "G ny nx"], ngroups: int) -> Float[Array, "ng ny nx"]:
    """The first ``ngroups`` of the per-group offsets (zeros past the ``G`` stored)."""
    n = min(ngroups, offsets_dn.shape[0])
    return jnp.pad(offsets_dn[:n], ((0, ngroups - n), (0, 0), (0, 0)))


def slopes(ramp: Float[Array, "ng ny nx"]) -> Float[Array, "ng-1 ny nx"]:
    """Group differences: what a calslope file's ``SLOPE`` holds (DN per group)."""
    return jnp.diff(ramp, axis=0)
