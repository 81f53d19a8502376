"""Warp kernels for the total variation of a block of the canonical density and colour grids.

For a block of ``n_x * n_y * n_z`` nodes with raw density ``d`` and colour logits ``c`` (3 channels)::

    tv = sum_a [ sum (d_{+a} - d)^2 / N_a  +  sum |c_{+a} - c|^2 / (3 N_a) ]

where ``N_a = (n_a - 1) n_x n_y n_z / n_a`` counts the neighbour pairs along axis ``a``: each term is the mean
over its pairs (and colour channels). The gradient at a node, from each of its up to six neighbours ``n``
along axis ``a``, is ``(2 / N_a) (x - x_n)`` (``2 / (3 N_a)`` for colour).

One thread walks one (x, y) row of nodes along z. The forward pass sums into one slot per launch piece; the
backward pass writes every node's gradient once (no atomics).
"""

import functools

import warp as wp

from .grid import grid_funcs
from .raymarch import OPTIONS


@functools.cache
def total_variation_kernels(dtype):
    """Forward and backward kernels for scalar type ``dtype``."""
    vec3 = grid_funcs(dtype).vec3

    @wp.func
    def pair(x: dtype, c: vec3, xn: dtype, cn: vec3):
        """One pair's squared difference, colour averaged over its channels."""
        dc = cn - c
        return (xn - x) * (xn - x) + wp.dot(dc, dc) / dtype(3.0)

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def tv_fwd(
        i0: int,
        density: wp.array3d(dtype=dtype),
        color: wp.array3d(dtype=vec3),
        inv_pairs: vec3,  # 1 / N_a
        sums: wp.array(dtype=dtype),  # (1,): this launch piece's sum
    ):
        row = wp.tid() + i0  # one thread per (x, y) row of nodes along z
        ny = density.shape[1]
        nz = density.shape[2]
        i = row // ny
        j = row - i * ny
        sx = dtype(0.0)
        sy = dtype(0.0)
        sz = dtype(0.0)
        for k in range(nz):
            x = density[i, j, k]
            c = color[i, j, k]
            if i + 1 < density.shape[0]:
                sx += pair(x, c, density[i + 1, j, k], color[i + 1, j, k])
            if j + 1 < ny:
                sy += pair(x, c, density[i, j + 1, k], color[i, j + 1, k])
            if k + 1 < nz:
                sz += pair(x, c, density[i, j, k + 1], color[i, j, k + 1])
        wp.atomic_add(sums, 0, inv_pairs[0] * sx + inv_pairs[1] * sy + inv_pairs[2] * sz)

    @wp.func
    def pull(x: dtype, c: vec3, xn: dtype, cn: vec3, k: dtype, gd: dtype, gc: vec3):
        """Add one neighbour's pull ``k (x - x_n)`` to the density and colour gradients."""
        return gd + k * (x - xn), gc + (k / dtype(3.0)) * (c - cn)

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def tv_bwd(
        i0: int,
        density: wp.array3d(dtype=dtype),
        color: wp.array3d(dtype=vec3),
        inv_pairs: vec3,
        g_tv: wp.array(dtype=dtype),
        grad_density: wp.array3d(dtype=dtype),
        grad_color: wp.array3d(dtype=vec3),
    ):
        row = wp.tid() + i0
        nx = density.shape[0]
        ny = density.shape[1]
        nz = density.shape[2]
        i = row // ny
        j = row - i * ny
        g = g_tv[0]  # the upstream gradient, read on the device
        kx = dtype(2.0) * g * inv_pairs[0]
        ky = dtype(2.0) * g * inv_pairs[1]
        kz = dtype(2.0) * g * inv_pairs[2]
        for k in range(nz):
            x = density[i, j, k]
            c = color[i, j, k]
            gd = dtype(0.0)
            gc = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
            if i > 0:
                gd, gc = pull(x, c, density[i - 1, j, k], color[i - 1, j, k], kx, gd, gc)
            if i + 1 < nx:
                gd, gc = pull(x, c, density[i + 1, j, k], color[i + 1, j, k], kx, gd, gc)
            if j > 0:
                gd, gc = pull(x, c, density[i, j - 1, k], color[i, j - 1, k], ky, gd, gc)
            if j + 1 < ny:
                gd, gc = pull(x, c, density[i, j + 1, k], color[i, j + 1, k], ky, gd, gc)
            if k > 0:
                gd, gc = pull(x, c, density[i, j, k - 1], color[i, j, k - 1], kz, gd, gc)
            if k + 1 < nz:
                gd, gc = pull(x, c, density[i, j, k + 1], color[i, j, k + 1], kz, gd, gc)
            grad_density[i, j, k] = gd
            grad_color[i, j, k] = gc

    return tv_fwd, tv_bwd
