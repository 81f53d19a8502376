"""Trilinear grid look-ups shared by the ray marcher and the skinning warp.

Grids are node-aligned over an axis-aligned box: node (i, j, k) of a grid with ``res`` nodes per
axis sits at ``bmin + (i, j, k) / scale`` with ``scale = (res - 1) / (bmax - bmin)`` (nodes per unit
length, precomputed on the host). A :class:`GridFrame` struct carries the three. Points outside the
box read zero and receive no gradient.
"""

import functools
from types import SimpleNamespace

import warp as wp


@functools.cache
def grid_funcs(dtype) -> SimpleNamespace:
    """Warp functions for grids of scalar type ``dtype`` (wp.float32 or wp.float64)."""
    vec3 = wp.types.vector(3, dtype)
    vec8 = wp.types.vector(8, dtype)

    @wp.struct
    class GridFrame:
        """Where a node-aligned grid lies: its first node, nodes per unit length, nodes per axis."""

        bmin: vec3
        scale: vec3
        res: wp.vec3i

    def make_frame(bmin, scale, res) -> GridFrame:
        """A :class:`GridFrame` from three Python triples (host side)."""
        frame = GridFrame()
        frame.bmin = vec3(*bmin)
        frame.scale = vec3(*scale)
        frame.res = wp.vec3i(*res)
        return frame

    @wp.func
    def locate(x: vec3, frame: GridFrame):
        """Cell base index, fractional position in the cell, and whether x lies in the box."""
        res = frame.res
        f = wp.cw_mul(x - frame.bmin, frame.scale)
        hi = vec3(dtype(res[0] - 1), dtype(res[1] - 1), dtype(res[2] - 1))
        ok = f[0] >= dtype(0.0) and f[1] >= dtype(0.0) and f[2] >= dtype(0.0)
        ok = ok and f[0] <= hi[0] and f[1] <= hi[1] and f[2] <= hi[2]  # also False for NaN
        base = wp.vec3i(0, 0, 0)
        frac = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        if ok:
            base = wp.vec3i(wp.min(int(f[0]), res[0] - 2), wp.min(int(f[1]), res[1] - 2), wp.min(int(f[2]), res[2] - 2))
            frac = f - vec3(dtype(base[0]), dtype(base[1]), dtype(base[2]))
        return ok, base, frac

    @wp.func
    def corner_weights(frac: vec3):
        """The 8 trilinear weights; bit 0/1/2 of the corner index selects the +x/+y/+z node."""
        x1 = frac[0]
        y1 = frac[1]
        z1 = frac[2]
        x0 = dtype(1.0) - x1
        y0 = dtype(1.0) - y1
        z0 = dtype(1.0) - z1
        return vec8(
            x0 * y0 * z0, x1 * y0 * z0, x0 * y1 * z0, x1 * y1 * z0,
            x0 * y0 * z1, x1 * y0 * z1, x0 * y1 * z1, x1 * y1 * z1,
        )  # fmt: skip

    @wp.func
    def corner_weight_grad(frac: vec3, c: int):
        """d corner_weight / d frac."""
        sx = dtype(1.0)
        wx = frac[0]
        if (c & 1) == 0:
            wx = dtype(1.0) - frac[0]
            sx = dtype(-1.0)
        sy = dtype(1.0)
        wy = frac[1]
        if (c & 2) == 0:
            wy = dtype(1.0) - frac[1]
            sy = dtype(-1.0)
        sz = dtype(1.0)
        wz = frac[2]
        if (c & 4) == 0:
            wz = dtype(1.0) - frac[2]
            sz = dtype(-1.0)
        return vec3(sx * wy * wz, wx * sy * wz, wx * wy * sz)

    @wp.func
    def lerp3(grid: wp.array3d(dtype=dtype), base: wp.vec3i, w8: vec8):
        v = dtype(0.0)
        for c in range(8):
            v += w8[c] * grid[base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2)]
        return v

    @wp.func
    def lerp3_grad(grid: wp.array3d(dtype=dtype), base: wp.vec3i, frac: vec3):
        """Gradient of the interpolated value with respect to ``frac``."""
        g = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for c in range(8):
            g += corner_weight_grad(frac, c) * grid[base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2)]
        return g

    @wp.func
    def scatter3(grid: wp.array3d(dtype=dtype), base: wp.vec3i, w8: vec8, value: dtype):
        for c in range(8):
            wp.atomic_add(grid, base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2), w8[c] * value)

    @wp.func
    def lerp3v(grid: wp.array3d(dtype=vec3), base: wp.vec3i, w8: vec8):
        v = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for c in range(8):
            v += w8[c] * grid[base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2)]
        return v

    @wp.func
    def lerp3v_dot_grad(grid: wp.array3d(dtype=vec3), base: wp.vec3i, frac: vec3, g: vec3):
        """Gradient of dot(g, interpolated vector) with respect to ``frac``."""
        out = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for c in range(8):
            v = grid[base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2)]
            out += corner_weight_grad(frac, c) * wp.dot(g, v)
        return out

    @wp.func
    def scatter3v(grid: wp.array3d(dtype=vec3), base: wp.vec3i, w8: vec8, value: vec3):
        for c in range(8):
            wp.atomic_add(grid, base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2), w8[c] * value)

    @wp.func
    def lerp4(grid: wp.array4d(dtype=dtype), ch: int, base: wp.vec3i, w8: vec8):
        v = dtype(0.0)
        for c in range(8):
            v += w8[c] * grid[ch, base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2)]
        return v

    @wp.func
    def value_and_grad(v: vec8, frac: vec3):
        """Trilinear value of 8 corner values and its gradient with respect to ``frac``."""
        x1 = frac[0]
        y1 = frac[1]
        z1 = frac[2]
        y0 = dtype(1.0) - y1
        z0 = dtype(1.0) - z1
        # Edges along x, y and z, then bilinear blends of them.
        ex00 = v[0] + x1 * (v[1] - v[0])
        ex10 = v[2] + x1 * (v[3] - v[2])
        ex01 = v[4] + x1 * (v[5] - v[4])
        ex11 = v[6] + x1 * (v[7] - v[6])
        face0 = ex00 + y1 * (ex10 - ex00)
        face1 = ex01 + y1 * (ex11 - ex01)
        value = face0 + z1 * (face1 - face0)
        gx = y0 * z0 * (v[1] - v[0]) + y1 * z0 * (v[3] - v[2]) + y0 * z1 * (v[5] - v[4]) + y1 * z1 * (v[7] - v[6])
        gy = z0 * (ex10 - ex00) + z1 * (ex11 - ex01)
        gz = face1 - face0
        return value, vec3(gx, gy, gz)

    @wp.func
    def corners4(grid: wp.array4d(dtype=dtype), ch: int, base: wp.vec3i):
        i = base[0]
        j = base[1]
        k = base[2]
        return vec8(
            grid[ch, i, j, k], grid[ch, i + 1, j, k], grid[ch, i, j + 1, k], grid[ch, i + 1, j + 1, k],
            grid[ch, i, j, k + 1], grid[ch, i + 1, j, k + 1], grid[ch, i, j + 1, k + 1], grid[ch, i + 1, j + 1, k + 1],
        )  # fmt: skip

    @wp.func
    def scatter4(grid: wp.array4d(dtype=dtype), ch: int, base: wp.vec3i, w8: vec8, value: dtype):
        for c in range(8):
            wp.atomic_add(
                grid,
                ch,
                base[0] + (c & 1),
                base[1] + ((c >> 1) & 1),
                base[2] + (c >> 2),
                w8[c] * value,
            )

    @wp.func
    def frac_to_world(g: vec3, frame: GridFrame):
        """Chain a gradient with respect to ``frac`` to one with respect to world position."""
        return wp.cw_mul(g, frame.scale)

    return SimpleNamespace(
        vec3=vec3,
        vec8=vec8,
        GridFrame=GridFrame,
        make_frame=make_frame,
        locate=locate,
        corner_weights=corner_weights,
        lerp3=lerp3,
        lerp3_grad=lerp3_grad,
        scatter3=scatter3,
        lerp3v=lerp3v,
        lerp3v_dot_grad=lerp3v_dot_grad,
        scatter3v=scatter3v,
        lerp4=lerp4,
        corners4=corners4,
        value_and_grad=value_and_grad,
        scatter4=scatter4,
        frac_to_world=frac_to_world,
    )
