"""Warp kernels for linear blend skinning in both directions.

* ``inverse_lbs``: HumanNeRF's observation -> canonical warp. For each bone ``b`` the point is moved
  by that bone's observation->canonical transform, ``y_b = R_b x + t_b``, the bone's weight is read
  from a canonical motion-weight volume at ``y_b``, and the candidates are blended with weights
  sharpened by the integer exponent ``k``: ``x_c = sum_b u_b y_b / sum_b u_b`` with ``u_b = (w_b / m)^k``,
  ``m = max_b w_b`` (``k = 1``: HumanNeRF's ``sum_b w_b y_b / sum_b w_b``). ``fg = sum_b w_b`` is the
  foreground likelihood. Dividing by ``m`` changes nothing in ``x_c`` but keeps ``sum_b u_b >= 1``
  (no shrinking towards the origin where all weights are small). With a gate ``r > 0`` only candidates
  within ``r`` of the dominant bone's candidate ``y_top`` (``top = argmax_b w_b``) are blended
  (``u_b = 0`` beyond): where a hand hangs beside the hip, the wrist's and the thigh's candidates both
  carry weight but lie far apart in canonical space, and their mean would land in empty room. One pass
  finds ``m`` and ``top``, a second blends. The bone count and ``k`` are compile-time constants of each
  kernel instance, the gate a runtime value.
* ``forward_lbs``: mesh vertices, canonical -> posed, with sparse per-vertex bone weights.

Adjoints are hand-written; which gradients to compute is a compile-time constant of each backward
kernel instance, so only those asked for cost anything. Every kernel takes the first item of its
launch (``i0``) so that a CPU launch can be split across threads.

Inverse-LBS backward: ``x_c`` does not change when every ``w_b`` is scaled alike, so ``m`` is a constant of
the derivative, as is the gate (piecewise constant). With ``su = sum_b u_b``, ``acc = sum_b u_b y_b`` and
``x_c = acc / max(su, eps)``, the incoming ``g_x`` and ``g_fg`` give ``dL/dacc = g_x / max(su, eps)`` and
``dL/dsu = -g_x . x_c / su`` (where ``su > eps``), so ``dL/du_b = dL/dacc . y_b + dL/dsu`` and ``dL/dw_b =
dL/du_b k u_b / w_b + g_fg`` (gated bones: ``g_fg``; scattered to the 8 weight nodes around ``y_b``), and
``dL/dy_b = u_b dL/dacc + dL/dw_b grad w_b(y_b)``, which ``y_b = R_b x + t_b`` carries to the bone
(``outer(dL/dy_b, x)``, ``dL/dy_b``) and to the point (``R_b^T dL/dy_b``).
"""

import functools
from types import SimpleNamespace

import warp as wp

from .grid import grid_funcs

OPTIONS = {"optimization_level": 3}


@functools.cache
def skinning_types(dtype) -> SimpleNamespace:
    """Vector and matrix types of scalar type ``dtype``, and the bundle both inverse-LBS passes read."""
    g = grid_funcs(dtype)
    vec3 = g.vec3
    mat33 = wp.types.matrix((3, 3), dtype)

    @wp.struct
    class Warp:
        """Per-bone observation -> canonical transforms and the canonical motion-weight volume."""

        rot: wp.array(dtype=mat33)
        trans: wp.array(dtype=vec3)
        weights: wp.array4d(dtype=dtype)
        frame: g.GridFrame
        eps: dtype
        gate: dtype  # blend only candidates this close to the dominant bone's (<= 0: all)

    vec2 = wp.types.vector(2, dtype)
    return SimpleNamespace(vec2=vec2, vec3=vec3, mat33=mat33, grid=g, Warp=Warp)


@functools.cache
def sharpen_funcs(dtype, k: int) -> SimpleNamespace:
    """``r^k`` and its derivative ``k r^(k-1)`` for a compile-time integer ``k`` >= 1, by multiplication."""
    K = k

    @wp.func
    def power(r: dtype):
        out = dtype(1.0)
        for _ in range(wp.static(K)):
            out = out * r
        return out

    @wp.func
    def power_grad(r: dtype):
        out = dtype(K)
        for _ in range(wp.static(K - 1)):
            out = out * r
        return out

    return SimpleNamespace(power=power, power_grad=power_grad)


@functools.cache
def inverse_lbs_forward(dtype, n_bones: int, sharpness: int = 1):
    """Inverse-LBS forward for ``n_bones`` bones (1..128), blend exponent ``sharpness`` and scalar type ``dtype``."""
    if not 1 <= n_bones <= 128:
        raise ValueError(f"n_bones must be in 1..128, got {n_bones}")
    st = skinning_types(dtype)
    g, vec3 = st.grid, st.vec3
    sh = sharpen_funcs(dtype, sharpness)
    NB = n_bones
    bone_weights = wp.types.vector(length=NB, dtype=dtype)

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def inverse_lbs_fwd(
        i0: int,
        points: wp.array(dtype=vec3),
        warp: st.Warp,
        out_x: wp.array(dtype=vec3),
        out_fg: wp.array(dtype=dtype),
        out_norm: wp.array(dtype=st.vec2),
        out_top: wp.array(dtype=wp.int32),
    ):
        i = wp.tid() + i0
        x = points[i]
        ws = bone_weights()
        s = dtype(0.0)
        m = dtype(0.0)
        top = int(0)
        for b in range(NB):  # every bone's weight at its candidate; the largest and its bone
            y = warp.rot[b] * x + warp.trans[b]
            ok, base, frac = g.locate(y, warp.frame)
            if ok:
                w = g.lerp4(warp.weights, b, base, g.corner_weights(frac))
                ws[b] = w
                s += w
                if w > m:
                    m = w
                    top = b
        y_top = warp.rot[top] * x + warp.trans[top]
        acc = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        su = dtype(0.0)
        if m > dtype(0.0):
            for b in range(NB):  # blend the candidates that lie within the gate of the dominant one
                if ws[b] > dtype(0.0):
                    y = warp.rot[b] * x + warp.trans[b]
                    if warp.gate <= dtype(0.0) or wp.length_sq(y - y_top) <= warp.gate * warp.gate:
                        u = sh.power(ws[b] / m)
                        acc += u * y
                        su += u
        out_x[i] = acc / wp.max(su, warp.eps)
        out_fg[i] = s
        out_norm[i] = st.vec2(m, su)
        out_top[i] = top

    return inverse_lbs_fwd


@functools.cache
def inverse_lbs_backward(dtype, n_bones: int, points: bool, weights: bool, bones: bool, sharpness: int = 1):
    """Inverse-LBS backward (see the module docstring), computing the gradients for ``points``,
    ``weights`` and ``bones`` (rotations and translations) that are asked for. The bone gradients are summed
    into ``copies`` copies of (B,) slots, point ``i`` into copy ``i % copies``: on a GPU every point of a
    launch adds into the same B bones, and one copy makes those atomics wait on each other."""
    st = skinning_types(dtype)
    sh = sharpen_funcs(dtype, sharpness)
    g, vec3, mat33 = st.grid, st.vec3, st.mat33
    NB, POINTS, WEIGHTS, BONES = n_bones, points, weights, bones

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def inverse_lbs_bwd(
        i0: int,
        points: wp.array(dtype=vec3),
        warp: st.Warp,
        out_x: wp.array(dtype=vec3),
        out_norm: wp.array(dtype=st.vec2),
        out_top: wp.array(dtype=wp.int32),
        grad_x: wp.array(dtype=vec3),
        grad_fg: wp.array(dtype=dtype),
        grad_points: wp.array(dtype=vec3),
        grad_weights: wp.array4d(dtype=dtype),
        grad_rot: wp.array(dtype=mat33),
        grad_trans: wp.array(dtype=vec3),
        copies: int,
    ):
        i = wp.tid() + i0
        slot = (i % copies) * NB  # this point's copy of the bone gradients (fewer threads per atomic address)
        x = points[i]
        m = out_norm[i][0]
        su = out_norm[i][1]
        msu = wp.max(su, warp.eps)
        gacc = grad_x[i] / msu
        gsu = dtype(0.0)
        if su > warp.eps:
            gsu = -wp.dot(grad_x[i], out_x[i]) / msu
        gfg = grad_fg[i]
        top = out_top[i]
        y_top = warp.rot[top] * x + warp.trans[top]
        gp = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for b in range(NB):
            y = warp.rot[b] * x + warp.trans[b]
            ok, base, frac = g.locate(y, warp.frame)
            if ok and m > dtype(0.0):
                w, gfrac = g.value_and_grad(g.corners4(warp.weights, b, base), frac)
                u = dtype(0.0)
                gw = gfg
                if warp.gate <= dtype(0.0) or wp.length_sq(y - y_top) <= warp.gate * warp.gate:
                    u = sh.power(w / m)
                    gw += (wp.dot(gacc, y) + gsu) * sh.power_grad(w / m) / m
                if wp.static(WEIGHTS):
                    g.scatter4(grad_weights, b, base, g.corner_weights(frac), gw)
                if wp.static(POINTS or BONES):
                    gy = u * gacc + gw * g.frac_to_world(gfrac, warp.frame)
                    if wp.static(BONES):
                        wp.atomic_add(grad_rot, slot + b, wp.outer(gy, x))
                        wp.atomic_add(grad_trans, slot + b, gy)
                    if wp.static(POINTS):
                        gp += wp.transpose(warp.rot[b]) * gy
        if wp.static(POINTS):
            grad_points[i] = gp

    return inverse_lbs_bwd


@functools.cache
def baked_warp_lookup(dtype):
    """Look-ups in a pose's baked inverse warp: a node-aligned (X, Y, Z) table of ``(fg * x_c, fg)`` read
    trilinearly, ``x_c = (fg x_c)~ / max(fg~, 1e-6)``, ``fg = fg~``; points outside the table get ``fg = 0``.
    ``sample`` is the look-up of one point (also used by the ray sampler), ``kernel`` that of many."""
    st = skinning_types(dtype)
    g, vec3 = st.grid, st.vec3
    vec4 = wp.types.vector(4, dtype)

    @wp.func
    def sample(x: vec3, table: wp.array3d(dtype=vec4), frame: g.GridFrame):
        ok, base, frac = g.locate(x, frame)
        acc = vec4(dtype(0.0), dtype(0.0), dtype(0.0), dtype(0.0))
        if ok:
            w8 = g.corner_weights(frac)
            for c in range(8):
                acc += w8[c] * table[base[0] + (c & 1), base[1] + ((c >> 1) & 1), base[2] + (c >> 2)]
        return vec3(acc[0], acc[1], acc[2]) / wp.max(acc[3], dtype(1e-6)), acc[3]

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def baked_lookup(
        i0: int,
        points: wp.array(dtype=vec3),
        table: wp.array3d(dtype=vec4),
        frame: g.GridFrame,
        out_x: wp.array(dtype=vec3),
        out_fg: wp.array(dtype=dtype),
    ):
        i = wp.tid() + i0
        x_c, fg = sample(points[i], table, frame)
        out_x[i] = x_c
        out_fg[i] = fg

    return SimpleNamespace(kernel=baked_lookup, sample=sample, vec4=vec4)


@functools.cache
def forward_lbs_forward(dtype):
    """Forward LBS of vertices with sparse (V, K) bone indices and weights."""
    st = skinning_types(dtype)
    vec3, mat33 = st.vec3, st.mat33

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def forward_lbs_fwd(
        i0: int,
        verts: wp.array(dtype=vec3),
        bone_idx: wp.array2d(dtype=wp.int32),
        bone_w: wp.array2d(dtype=dtype),
        rot: wp.array(dtype=mat33),
        trans: wp.array(dtype=vec3),
        out: wp.array(dtype=vec3),
    ):
        i = wp.tid() + i0
        x = verts[i]
        acc = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for k in range(bone_idx.shape[1]):
            w = bone_w[i, k]
            if w != dtype(0.0):
                b = int(bone_idx[i, k])
                acc += w * (rot[b] * x + trans[b])
        out[i] = acc

    return forward_lbs_fwd


@functools.cache
def forward_lbs_backward(dtype, verts: bool, bones: bool, weights: bool):
    """Forward-LBS backward, computing the gradients for ``verts``, ``bones`` and ``weights`` asked for.
    Bone gradients are summed with atomics: launch it as one piece on CPU."""
    st = skinning_types(dtype)
    vec3, mat33 = st.vec3, st.mat33
    VERTS, BONES, WEIGHTS = verts, bones, weights

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def forward_lbs_bwd(
        i0: int,
        verts: wp.array(dtype=vec3),
        bone_idx: wp.array2d(dtype=wp.int32),
        bone_w: wp.array2d(dtype=dtype),
        rot: wp.array(dtype=mat33),
        trans: wp.array(dtype=vec3),
        grad_out: wp.array(dtype=vec3),
        grad_verts: wp.array(dtype=vec3),
        grad_rot: wp.array(dtype=mat33),
        grad_trans: wp.array(dtype=vec3),
        grad_w: wp.array2d(dtype=dtype),
    ):
        i = wp.tid() + i0
        x = verts[i]
        go = grad_out[i]
        gx = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for k in range(bone_idx.shape[1]):
            w = bone_w[i, k]
            b = int(bone_idx[i, k])
            if wp.static(WEIGHTS):
                grad_w[i, k] = wp.dot(go, rot[b] * x + trans[b])
            if w != dtype(0.0):
                if wp.static(VERTS):
                    gx += w * (wp.transpose(rot[b]) * go)
                if wp.static(BONES):
                    wp.atomic_add(grad_rot, b, w * wp.outer(go, x))
                    wp.atomic_add(grad_trans, b, w * go)
        if wp.static(VERTS):
            grad_verts[i] = gx

    return forward_lbs_bwd
