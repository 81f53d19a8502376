"""Warp kernels for volume ray marching over an explicit density + colour grid.

Samples are *packed*: ray ``r`` owns samples ``offsets[r] .. offsets[r+1]`` (nerfacc's layout),
so empty space skipped by the occupancy grid costs nothing downstream. Every kernel takes the
first item of its launch (``r0``) so that a CPU launch can be split across threads; its switches
(jitter, occupancy, which outputs and gradients) are compile-time constants of each kernel
instance, as the scalar type is.

Compositing (per ray, samples ``i = 0 .. n-1`` front to back, stopped once ``T < t_thresh``)::

    sigma_i = act(density(x_i)) ,  a_i = fg_i * (1 - exp(-sigma_i * delta_i)) ,  c_i = sigmoid(colour(x_i))
    T_0 = 1 ,  T_{i+1} = T_i * (1 - a_i) ,  w_i = T_i * a_i
    C = sum_i w_i c_i ,  A = sum_i w_i = 1 - T_n ,  D = sum_i w_i t_i

The backward pass (hand-written: ``wp.Tape`` is wrong for loops with ``break``) needs the
derivative of each output with respect to each ``a_i``. Split ``C`` at sample ``i``::

    C = sum_{j<i} w_j c_j + T_i a_i c_i + T_i (1 - a_i) B_i ,
    B_i = sum_{j>i} (T_j / T_{i+1}) a_j c_j      (the normalised colour behind sample i)

so ``dC/da_i = T_i (c_i - B_i)``, and likewise ``dA/da_i = T_i (1 - BA_i)`` and
``dD/da_i = T_i (t_i - BD_i)`` with ``BA_i``, ``BD_i`` the opacity and depth behind ``i``. Walking the
ray back to front, all three follow one recurrence from ``B_{n-1} = 0``::

    B_{i-1} = a_i c_i + (1 - a_i) B_i

which only multiplies by ``1 - a_i``: no division by a vanishing transmittance. The forward pass saves
``T_i``, the raw density, ``exp(-sigma_i delta_i)`` and ``c_i`` of every sample, so the backward pass
reads the grids again only for gradients with respect to sample positions. The chain rule then gives
``da_i/draw_i = fg_i exp(-sigma_i delta_i) delta_i act'(raw_i)``, ``da_i/dfg_i = 1 - exp(-sigma_i delta_i)``,
``dC/dc_i = w_i`` (times the sigmoid's ``c (1 - c)``), and the trilinear weights carry every raw gradient
to the 8 grid nodes around ``x_i`` and to ``x_i`` itself.

Density activations: 0 = relu (HumanNeRF), 1 = softplus. Colour activation: sigmoid.
"""

import functools
from types import SimpleNamespace

import warp as wp

from .grid import grid_funcs
from .skinning import baked_warp_lookup

ACT_RELU = 0
ACT_SOFTPLUS = 1
OPTIONS = {"optimization_level": 3}


@functools.cache
def sampling_kernels(dtype, jitter: bool, use_occupancy: bool, baked: bool = False) -> SimpleNamespace:
    """Stratified sampling inside a box for scalar type ``dtype``: a counting pass places every sample and keeps
    its ``t`` (or -1 where it is dropped), a filling pass packs the kept ones.

    A sample is dropped where the observation-space occupancy grid is empty (``use_occupancy``). With ``baked``
    each sample is also warped to canonical space by a pose's baked inverse warp (``skinning.baked_warp_lookup``)
    and dropped where its foreground likelihood is 0 (it would add nothing); the packed samples then carry
    canonical positions and their foreground likelihood."""
    g = grid_funcs(dtype)
    vec3 = g.vec3
    lookup = baked_warp_lookup(dtype)
    vec4 = lookup.vec4
    JITTER, USE_OCC, BAKED = jitter, use_occupancy, baked

    @wp.struct
    class BakedWarp:
        """A pose's baked inverse warp: the table and where it lies."""

        table: wp.array3d(dtype=vec4)
        frame: g.GridFrame

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
    def sample_t(ray: int, k: int, n: int, near: dtype, far: dtype, seed: int):
        u = dtype(0.5)
        if wp.static(JITTER):
            state = wp.rand_init(seed, ray * n + k)
            u = dtype(wp.randf(state))
        step = (far - near) / dtype(n)
        return near + (dtype(k) + u) * step, step

    @wp.func
    def occupied(x: vec3, bmin: vec3, bmax: vec3, occ: wp.array3d(dtype=wp.uint8)):
        if wp.static(USE_OCC):
            idx = wp.vec3i(0, 0, 0)
            for a in range(3):
                n = occ.shape[a]
                f = (x[a] - bmin[a]) / (bmax[a] - bmin[a]) * dtype(n)
                idx[a] = wp.clamp(int(wp.floor(f)), 0, n - 1)
            return occ[idx[0], idx[1], idx[2]] != wp.uint8(0)
        return True

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def count_samples(
        r0: int,
        origins: wp.array(dtype=vec3),
        dirs: wp.array(dtype=vec3),
        bmin: vec3,
        bmax: vec3,
        n_samples: int,
        seed: int,
        occ: wp.array3d(dtype=wp.uint8),
        warp: BakedWarp,
        counts: wp.array(dtype=wp.int32),
        kept_t: wp.array(dtype=dtype),  # (rays * n_samples,) each sample's t, or -1 where it is dropped
        kept_x: wp.array(dtype=vec3),  # with ``baked``: its canonical position (else empty)
        kept_fg: wp.array(dtype=dtype),  # with ``baked``: its foreground likelihood (else empty)
        steps: wp.array(dtype=dtype),  # (rays,) the bin length
    ):
        r = wp.tid() + r0
        o = origins[r]
        d = dirs[r]
        near, far = ray_box(o, d, bmin, bmax)
        c = int(0)
        step = dtype(0.0)
        for k in range(n_samples):
            t = dtype(-1.0)
            x = o
            if far > near:
                t, step = sample_t(r, k, n_samples, near, far, seed)
                x = o + t * d
                if not occupied(x, bmin, bmax, occ):
                    t = dtype(-1.0)
            if wp.static(BAKED):
                if t >= dtype(0.0):
                    x_c, fg = lookup.sample(x, warp.table, warp.frame)
                    if fg > dtype(0.0):
                        kept_x[r * n_samples + k] = x_c
                        kept_fg[r * n_samples + k] = fg
                    else:
                        t = dtype(-1.0)
            if t >= dtype(0.0):
                c += 1
            kept_t[r * n_samples + k] = t
        counts[r] = wp.int32(c)
        steps[r] = step

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def fill_samples(
        r0: int,
        origins: wp.array(dtype=vec3),
        dirs: wp.array(dtype=vec3),
        n_samples: int,
        kept_t: wp.array(dtype=dtype),
        kept_x: wp.array(dtype=vec3),
        kept_fg: wp.array(dtype=dtype),
        steps: wp.array(dtype=dtype),
        offsets: wp.array(dtype=wp.int32),
        t_mid: wp.array(dtype=dtype),
        deltas: wp.array(dtype=dtype),
        ray_ids: wp.array(dtype=wp.int32),
        positions: wp.array(dtype=vec3),
        fg: wp.array(dtype=dtype),
    ):
        r = wp.tid() + r0
        s = int(offsets[r])
        if int(offsets[r + 1]) == s:
            return
        o = origins[r]
        d = dirs[r]
        step = steps[r]
        for k in range(n_samples):
            t = kept_t[r * n_samples + k]
            if t >= dtype(0.0):
                t_mid[s] = t
                deltas[s] = step
                ray_ids[s] = wp.int32(r)
                if wp.static(BAKED):
                    positions[s] = kept_x[r * n_samples + k]
                    fg[s] = kept_fg[r * n_samples + k]
                else:
                    positions[s] = o + t * d
                s += 1

    return SimpleNamespace(vec3=vec3, vec4=vec4, grid=g, BakedWarp=BakedWarp, count=count_samples, fill=fill_samples)


@functools.cache
def composite_structs(dtype) -> SimpleNamespace:
    """The argument bundles shared by the compositing kernels of scalar type ``dtype``."""
    g = grid_funcs(dtype)
    vec3 = g.vec3

    @wp.struct
    class RaySamples:
        """Packed samples: where to read the grids, where they lie on their ray, and their fg weight; ``order``
        is the order in which the rays are processed (see :func:`ray_order_keys`)."""

        order: wp.array(dtype=wp.int32)
        offsets: wp.array(dtype=wp.int32)
        positions: wp.array(dtype=vec3)
        t_mid: wp.array(dtype=dtype)
        deltas: wp.array(dtype=dtype)
        fg: wp.array(dtype=dtype)

    @wp.struct
    class RadianceGrid:
        density: wp.array3d(dtype=dtype)
        color: wp.array3d(dtype=vec3)
        frame: g.GridFrame

    @wp.struct
    class RayOutputs:
        """Per ray colour, opacity and depth (or their incoming gradients in the backward pass)."""

        rgb: wp.array(dtype=vec3)
        alpha: wp.array(dtype=dtype)
        depth: wp.array(dtype=dtype)

    @wp.struct
    class Saved:
        """What the forward pass keeps for the backward: per sample the transmittance ``T_i``, the raw
        density, ``exp(-sigma_i delta_i)`` and the activated colour (empty without ``rgb``); per ray the
        samples used."""

        trans: wp.array(dtype=dtype)
        raw: wp.array(dtype=dtype)
        extinction: wp.array(dtype=dtype)
        color: wp.array(dtype=vec3)
        n_used: wp.array(dtype=wp.int32)

    @wp.struct
    class Gradients:
        density: wp.array3d(dtype=dtype)
        color: wp.array3d(dtype=vec3)
        positions: wp.array(dtype=vec3)
        fg: wp.array(dtype=dtype)

    return SimpleNamespace(
        vec3=vec3,
        grid=g,
        RaySamples=RaySamples,
        RadianceGrid=RadianceGrid,
        RayOutputs=RayOutputs,
        Saved=Saved,
        Gradients=Gradients,
    )


ORDER_CELLS = 32  # cells per axis of the lattice whose Morton order orders the rays
ORDER_MIN_RAYS = 4096  # smaller launches keep their rays' order (ordering them costs more than it saves)


@functools.cache
def ray_order_keys(dtype):
    """Sort keys that put rays reading the same part of a grid next to each other: the Morton code of the cell of
    the ``ORDER_CELLS``^3 lattice ``frame`` that holds the ray's middle sample (samples outside count as in the
    nearest cell), ``ORDER_CELLS``^3 for a ray without samples (those come last).

    The compositing kernels read 8 grid nodes per sample; rays that come in random order fetch each node's cache
    line anew, neighbouring rays share them (and on CPU each thread's piece of the launch covers one region).
    """
    g = grid_funcs(dtype)
    CELLS = ORDER_CELLS
    BITS = CELLS.bit_length() - 1

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def ray_keys(
        r0: int,
        offsets: wp.array(dtype=wp.int32),
        positions: wp.array(dtype=g.vec3),
        frame: g.GridFrame,
        keys: wp.array(dtype=wp.int32),
    ):
        r = wp.tid() + r0
        begin = offsets[r]
        end = offsets[r + 1]
        key = int(CELLS * CELLS * CELLS)
        if end > begin:
            f = wp.cw_mul(positions[(begin + end) // 2] - frame.bmin, frame.scale)
            key = int(0)
            for a in range(3):
                c = int(wp.clamp(f[a], dtype(0.0), dtype(CELLS - 1)))
                for b in range(BITS):
                    key = key | (((c >> b) & 1) << (3 * b + a))
        keys[r] = wp.int32(key)

    return ray_keys


@functools.cache
def activation_funcs(dtype, act: int) -> SimpleNamespace:
    """The density activation ``act`` and its derivative, and the colour sigmoid."""
    ACT = act

    @wp.func
    def activate(raw: dtype):
        if wp.static(ACT == ACT_RELU):
            return wp.max(raw, dtype(0.0))
        if raw > dtype(20.0):
            return raw
        return wp.log(dtype(1.0) + wp.exp(raw))

    @wp.func
    def activate_grad(raw: dtype):
        if wp.static(ACT == ACT_RELU):
            if raw > dtype(0.0):
                return dtype(1.0)
            return dtype(0.0)
        return dtype(1.0) / (dtype(1.0) + wp.exp(-raw))

    vec3 = grid_funcs(dtype).vec3

    @wp.func
    def sigmoid3(v: vec3):
        return vec3(
            dtype(1.0) / (dtype(1.0) + wp.exp(-v[0])),
            dtype(1.0) / (dtype(1.0) + wp.exp(-v[1])),
            dtype(1.0) / (dtype(1.0) + wp.exp(-v[2])),
        )

    return SimpleNamespace(activate=activate, activate_grad=activate_grad, sigmoid3=sigmoid3)


@functools.cache
def composite_forward(dtype, act: int, has_fg: bool, rgb: bool, depth: bool, save: bool):
    """Forward compositing: ``rgb``/``depth`` say which outputs to compute (opacity always), ``save``
    whether to keep the transmittance for a backward pass, ``has_fg`` whether alphas are scaled by fg."""
    st = composite_structs(dtype)
    g, vec3 = st.grid, st.vec3
    fn = activation_funcs(dtype, act)
    HAS_FG, RGB, DEPTH, SAVE = has_fg, rgb, depth, save

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def composite_fwd(
        r0: int,
        samples: st.RaySamples,
        grid: st.RadianceGrid,
        t_thresh: dtype,
        out: st.RayOutputs,
        saved: st.Saved,
    ):
        r = samples.order[wp.tid() + r0]
        begin = int(samples.offsets[r])
        end = int(samples.offsets[r + 1])
        T = dtype(1.0)
        C = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        D = dtype(0.0)
        used = int(0)
        for s in range(begin, end):
            if T < t_thresh:
                break
            if wp.static(SAVE):
                saved.trans[s] = T
            used += 1
            ok, base, frac = g.locate(samples.positions[s], grid.frame)
            if ok:
                w8 = g.corner_weights(frac)
                raw = g.lerp3(grid.density, base, w8)
                e = wp.exp(-fn.activate(raw) * samples.deltas[s])
                a = dtype(1.0) - e
                if wp.static(HAS_FG):
                    a = a * samples.fg[s]
                if wp.static(SAVE):
                    saved.raw[s] = raw
                    saved.extinction[s] = e
                w = T * a
                if wp.static(RGB):
                    c = fn.sigmoid3(g.lerp3v(grid.color, base, w8))
                    if wp.static(SAVE):
                        saved.color[s] = c
                    C += w * c
                if wp.static(DEPTH):
                    D += w * samples.t_mid[s]
                T = T * (dtype(1.0) - a)
        out.alpha[r] = dtype(1.0) - T
        if wp.static(RGB):
            out.rgb[r] = C
        if wp.static(DEPTH):
            out.depth[r] = D
        if wp.static(SAVE):
            saved.n_used[r] = wp.int32(used)

    return composite_fwd


@functools.cache
def composite_backward(dtype, act: int, has_fg: bool, rgb: bool, depth: bool, grids: bool, positions: bool):
    """Backward compositing (see the module docstring): gradients for the grids (``grids``), the sample
    positions (``positions``) and, with ``has_fg``, the fg weights, from those of the requested outputs."""
    st = composite_structs(dtype)
    g, vec3 = st.grid, st.vec3
    fn = activation_funcs(dtype, act)
    HAS_FG, RGB, DEPTH, GRIDS, POSITIONS = has_fg, rgb, depth, grids, positions

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def composite_bwd(
        r0: int,
        samples: st.RaySamples,
        grid: st.RadianceGrid,
        saved: st.Saved,
        grad_out: st.RayOutputs,
        grad_in: st.Gradients,
    ):
        r = samples.order[wp.tid() + r0]
        begin = int(samples.offsets[r])
        used = int(saved.n_used[r])
        gA = grad_out.alpha[r]
        gC = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        if wp.static(RGB):
            gC = grad_out.rgb[r]
        gD = dtype(0.0)
        if wp.static(DEPTH):
            gD = grad_out.depth[r]
        # Normalised colour, opacity and depth of everything behind the current sample.
        B = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        BA = dtype(0.0)
        BD = dtype(0.0)
        for j in range(used):
            s = begin + used - 1 - j
            ok, base, frac = g.locate(samples.positions[s], grid.frame)
            if ok:
                T = saved.trans[s]
                w8 = g.corner_weights(frac)
                raw = saved.raw[s]
                e = saved.extinction[s]
                a0 = dtype(1.0) - e
                f = dtype(1.0)
                if wp.static(HAS_FG):
                    f = samples.fg[s]
                a = f * a0
                c = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
                ga = gA * T * (dtype(1.0) - BA)  # dL/da_i
                gpos = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
                if wp.static(RGB):
                    c = saved.color[s]
                    ga += wp.dot(gC, T * (c - B))
                    gc = (T * a) * gC
                    graw_c = vec3(
                        gc[0] * c[0] * (dtype(1.0) - c[0]),
                        gc[1] * c[1] * (dtype(1.0) - c[1]),
                        gc[2] * c[2] * (dtype(1.0) - c[2]),
                    )
                    if wp.static(GRIDS):
                        g.scatter3v(grad_in.color, base, w8, graw_c)
                    if wp.static(POSITIONS):
                        gpos += g.lerp3v_dot_grad(grid.color, base, frac, graw_c)
                if wp.static(DEPTH):
                    ga += gD * T * (samples.t_mid[s] - BD)
                graw = ga * f * e * samples.deltas[s] * fn.activate_grad(raw)
                if wp.static(GRIDS):
                    g.scatter3(grad_in.density, base, w8, graw)
                if wp.static(POSITIONS):
                    gpos += graw * g.lerp3_grad(grid.density, base, frac)
                    grad_in.positions[s] = g.frac_to_world(gpos, grid.frame)
                if wp.static(HAS_FG):
                    grad_in.fg[s] = ga * a0
                B = a * c + (dtype(1.0) - a) * B
                BA = a + (dtype(1.0) - a) * BA
                BD = a * samples.t_mid[s] + (dtype(1.0) - a) * BD

    return composite_bwd
