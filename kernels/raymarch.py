"""Warp kernels for volume ray marching over an explicit density + colour grid.

Samples are *packed*: ray ``r`` owns samples ``offsets[r] .. offsets[r+1]`` (nerfacc's layout),
so empty space skipped by the occupancy grid costs nothing downstream. The compositing adjoint is
written by hand (``wp.Tape`` is wrong for loops with ``break``): it walks each ray backwards with
the transmittance saved by the forward pass and stable "behind" accumulators, so no division by a
vanishing transmittance ever happens.

Density activations: 0 = relu (HumanNeRF), 1 = softplus. Colour activation: sigmoid.
"""

import functools
from types import SimpleNamespace

import warp as wp

from .grid import grid_funcs

ACT_RELU = 0
ACT_SOFTPLUS = 1


@functools.cache
def raymarch_kernels(dtype) -> SimpleNamespace:
    """Sampling and compositing kernels for scalar type ``dtype``."""
    g = grid_funcs(dtype)
    vec3 = g.vec3

    @wp.func
    def ray_box(o: vec3, d: vec3, bmin: vec3, bmax: vec3):
        """Slab test; returns (near, far) with near >= 0. A miss gives far <= near."""
        tmin = dtype(0.0)
        tmax = dtype(1.0e30)
        for a in range(3):
            if wp.abs(d[a]) < dtype(1.0e-20):
                if o[a] < bmin[a] or o[a] > bmax[a]:
                    tmax = dtype(-1.0)
            else:
                inv = dtype(1.0) / d[a]
                t0 = (bmin[a] - o[a]) * inv
                t1 = (bmax[a] - o[a]) * inv
                tmin = wp.max(tmin, wp.min(t0, t1))
                tmax = wp.min(tmax, wp.max(t0, t1))
        return tmin, tmax

    @wp.func
    def sample_t(ray: int, k: int, n: int, near: dtype, far: dtype, jitter: int, seed: int):
        u = dtype(0.5)
        if jitter != 0:
            state = wp.rand_init(seed, ray * n + k)
            u = dtype(wp.randf(state))
        step = (far - near) / dtype(n)
        return near + (dtype(k) + u) * step, step

    @wp.func
    def occupied(x: vec3, bmin: vec3, bmax: vec3, occ: wp.array3d(dtype=wp.uint8)):
        idx = wp.vec3i(0, 0, 0)
        for a in range(3):
            n = occ.shape[a]
            f = (x[a] - bmin[a]) / (bmax[a] - bmin[a]) * dtype(n)
            idx[a] = wp.clamp(int(wp.floor(f)), 0, n - 1)
        return occ[idx[0], idx[1], idx[2]] != wp.uint8(0)

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def count_samples(
        origins: wp.array(dtype=vec3),
        dirs: wp.array(dtype=vec3),
        bmin: vec3,
        bmax: vec3,
        n_samples: int,
        jitter: int,
        seed: int,
        occ: wp.array3d(dtype=wp.uint8),
        use_occ: int,
        counts: wp.array(dtype=wp.int32),
    ):
        r = wp.tid()
        o = origins[r]
        d = dirs[r]
        near, far = ray_box(o, d, bmin, bmax)
        c = int(0)
        if far > near:
            if use_occ == 0:
                c = n_samples
            else:
                for k in range(n_samples):
                    t, step = sample_t(r, k, n_samples, near, far, jitter, seed)
                    if occupied(o + t * d, bmin, bmax, occ):
                        c += 1
        counts[r] = wp.int32(c)

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def fill_samples(
        origins: wp.array(dtype=vec3),
        dirs: wp.array(dtype=vec3),
        bmin: vec3,
        bmax: vec3,
        n_samples: int,
        jitter: int,
        seed: int,
        occ: wp.array3d(dtype=wp.uint8),
        use_occ: int,
        offsets: wp.array(dtype=wp.int32),
        t_mid: wp.array(dtype=dtype),
        deltas: wp.array(dtype=dtype),
        ray_ids: wp.array(dtype=wp.int32),
        positions: wp.array(dtype=vec3),
    ):
        r = wp.tid()
        begin = int(offsets[r])
        end = int(offsets[r + 1])
        if end == begin:
            return
        o = origins[r]
        d = dirs[r]
        near, far = ray_box(o, d, bmin, bmax)
        s = begin
        for k in range(n_samples):
            if s < end:
                t, step = sample_t(r, k, n_samples, near, far, jitter, seed)
                x = o + t * d
                keep = True
                if use_occ != 0:
                    keep = occupied(x, bmin, bmax, occ)
                if keep:
                    t_mid[s] = t
                    deltas[s] = step
                    ray_ids[s] = wp.int32(r)
                    positions[s] = x
                    s += 1

    @wp.func
    def activate(raw: dtype, act: int):
        if act == 0:
            return wp.max(raw, dtype(0.0))
        if raw > dtype(20.0):
            return raw
        return wp.log(dtype(1.0) + wp.exp(raw))

    @wp.func
    def activate_grad(raw: dtype, act: int):
        if act == 0:
            if raw > dtype(0.0):
                return dtype(1.0)
            return dtype(0.0)
        return dtype(1.0) / (dtype(1.0) + wp.exp(-raw))

    @wp.func
    def sigmoid3(v: vec3):
        return vec3(
            dtype(1.0) / (dtype(1.0) + wp.exp(-v[0])),
            dtype(1.0) / (dtype(1.0) + wp.exp(-v[1])),
            dtype(1.0) / (dtype(1.0) + wp.exp(-v[2])),
        )

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def composite_fwd(
        ray0: int,
        offsets: wp.array(dtype=wp.int32),
        positions: wp.array(dtype=vec3),
        t_mid: wp.array(dtype=dtype),
        deltas: wp.array(dtype=dtype),
        fg: wp.array(dtype=dtype),
        has_fg: int,
        density: wp.array3d(dtype=dtype),
        color: wp.array3d(dtype=vec3),
        bmin: vec3,
        scale: vec3,
        res: wp.vec3i,
        act: int,
        t_thresh: dtype,
        need_rgb: int,
        need_depth: int,
        save: int,
        rgb: wp.array(dtype=vec3),
        acc: wp.array(dtype=dtype),
        depth: wp.array(dtype=dtype),
        trans: wp.array(dtype=dtype),
        n_used: wp.array(dtype=wp.int32),
    ):
        r = wp.tid() + ray0
        begin = int(offsets[r])
        end = int(offsets[r + 1])
        T = dtype(1.0)
        C = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        D = dtype(0.0)
        used = int(0)
        for s in range(begin, end):
            if T < t_thresh:
                break
            if save != 0:
                trans[s] = T
            used += 1
            ok, base, frac = g.locate(positions[s], bmin, scale, res)
            if ok:
                w8 = g.corner_weights(frac)
                sigma = activate(g.lerp3(density, base, w8), act)
                a = dtype(1.0) - wp.exp(-sigma * deltas[s])
                if has_fg != 0:
                    a = a * fg[s]
                w = T * a
                if need_rgb != 0:
                    C += w * sigmoid3(g.lerp3v(color, base, w8))
                if need_depth != 0:
                    D += w * t_mid[s]
                T = T * (dtype(1.0) - a)
        acc[r] = dtype(1.0) - T
        if need_rgb != 0:
            rgb[r] = C
        if need_depth != 0:
            depth[r] = D
        if save != 0:
            n_used[r] = wp.int32(used)

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def composite_bwd(
        ray0: int,
        offsets: wp.array(dtype=wp.int32),
        positions: wp.array(dtype=vec3),
        t_mid: wp.array(dtype=dtype),
        deltas: wp.array(dtype=dtype),
        fg: wp.array(dtype=dtype),
        has_fg: int,
        density: wp.array3d(dtype=dtype),
        color: wp.array3d(dtype=vec3),
        bmin: vec3,
        scale: vec3,
        res: wp.vec3i,
        act: int,
        need_rgb: int,
        need_depth: int,
        trans: wp.array(dtype=dtype),
        n_used: wp.array(dtype=wp.int32),
        grad_rgb: wp.array(dtype=vec3),
        grad_acc: wp.array(dtype=dtype),
        grad_depth: wp.array(dtype=dtype),
        need_grid: int,
        need_pos: int,
        grad_density: wp.array3d(dtype=dtype),
        grad_color: wp.array3d(dtype=vec3),
        grad_pos: wp.array(dtype=vec3),
        grad_fg: wp.array(dtype=dtype),
    ):
        r = wp.tid() + ray0
        begin = int(offsets[r])
        used = int(n_used[r])
        gA = grad_acc[r]
        gC = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        if need_rgb != 0:
            gC = grad_rgb[r]
        gD = dtype(0.0)
        if need_depth != 0:
            gD = grad_depth[r]
        # Normalised colour, opacity and depth of everything behind the current sample.
        B = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        BA = dtype(0.0)
        BD = dtype(0.0)
        for j in range(used):
            s = begin + used - 1 - j
            ok, base, frac = g.locate(positions[s], bmin, scale, res)
            if ok:
                T = trans[s]
                w8 = g.corner_weights(frac)
                raw = g.lerp3(density, base, w8)
                sigma = activate(raw, act)
                e = wp.exp(-sigma * deltas[s])
                a0 = dtype(1.0) - e
                f = dtype(1.0)
                if has_fg != 0:
                    f = fg[s]
                a = f * a0
                c = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
                ga = gA * T * (dtype(1.0) - BA)
                gpos = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
                if need_rgb != 0:
                    c = sigmoid3(g.lerp3v(color, base, w8))
                    ga += wp.dot(gC, T * (c - B))
                    gc = (T * a) * gC
                    graw_c = vec3(
                        gc[0] * c[0] * (dtype(1.0) - c[0]),
                        gc[1] * c[1] * (dtype(1.0) - c[1]),
                        gc[2] * c[2] * (dtype(1.0) - c[2]),
                    )
                    if need_grid != 0:
                        g.scatter3v(grad_color, base, w8, graw_c)
                    if need_pos != 0:
                        gpos += g.lerp3v_dot_grad(color, base, frac, graw_c)
                if need_depth != 0:
                    ga += gD * T * (t_mid[s] - BD)
                graw = ga * f * e * deltas[s] * activate_grad(raw, act)
                if need_grid != 0:
                    g.scatter3(grad_density, base, w8, graw)
                if need_pos != 0:
                    gpos += graw * g.lerp3_grad(density, base, frac)
                    grad_pos[s] = g.frac_to_world(gpos, scale)
                if has_fg != 0:
                    grad_fg[s] = ga * a0
                B = a * c + (dtype(1.0) - a) * B
                BA = a + (dtype(1.0) - a) * BA
                BD = a * t_mid[s] + (dtype(1.0) - a) * BD

    return SimpleNamespace(
        vec3=vec3,
        count_samples=count_samples,
        fill_samples=fill_samples,
        composite_fwd=composite_fwd,
        composite_bwd=composite_bwd,
    )
