"""Warp kernels for linear blend skinning in both directions.

* ``inverse_lbs``: HumanNeRF's observation -> canonical warp. For each bone ``b`` the point is moved
  by that bone's observation->canonical transform, ``y_b = R_b x + t_b``, the bone's weight is read
  from a canonical motion-weight volume at ``y_b``, and
  ``x_c = sum_b w_b y_b / max(sum_b w_b, eps)``; ``fg = sum_b w_b`` is the foreground likelihood.
  The bone count is a compile-time constant of each kernel instance.
* ``forward_lbs``: mesh vertices, canonical -> posed, with sparse per-vertex bone weights.

Adjoints are hand-written; which gradients to compute is a compile-time constant of each backward
kernel instance, so only those asked for cost anything. Every kernel takes the first item of its
launch (``i0``) so that a CPU launch can be split across threads.

Inverse-LBS backward: with ``s = sum_b w_b``, ``acc = sum_b w_b y_b`` and ``x_c = acc / max(s, eps)``,
the incoming ``g_x`` and ``g_fg`` give ``dL/dacc = g_x / max(s, eps)`` and ``dL/ds = g_fg - g_x . x_c /
s`` (the second part only where ``s > eps``), so ``dL/dw_b = dL/dacc . y_b + dL/ds`` (scattered to the 8
weight nodes around ``y_b``) and ``dL/dy_b = w_b dL/dacc + dL/dw_b grad w_b(y_b)``, which ``y_b = R_b x +
t_b`` carries to the bone (``outer(dL/dy_b, x)``, ``dL/dy_b``) and to the point (``R_b^T dL/dy_b``).
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

    return SimpleNamespace(vec3=vec3, mat33=mat33, grid=g, Warp=Warp)


@functools.cache
def inverse_lbs_forward(dtype, n_bones: int):
    """Inverse-LBS forward for ``n_bones`` bones (1..128) and scalar type ``dtype``."""
    if not 1 <= n_bones <= 128:
        raise ValueError(f"n_bones must be in 1..128, got {n_bones}")
    st = skinning_types(dtype)
    g, vec3 = st.grid, st.vec3
    NB = n_bones

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def inverse_lbs_fwd(
        i0: int,
        points: wp.array(dtype=vec3),
        warp: st.Warp,
        out_x: wp.array(dtype=vec3),
        out_fg: wp.array(dtype=dtype),
    ):
        i = wp.tid() + i0
        x = points[i]
        acc = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        s = dtype(0.0)
        for b in range(NB):
            y = warp.rot[b] * x + warp.trans[b]
            ok, base, frac = g.locate(y, warp.frame)
            if ok:
                w = g.lerp4(warp.weights, b, base, g.corner_weights(frac))
                acc += w * y
                s += w
        out_x[i] = acc / wp.max(s, warp.eps)
        out_fg[i] = s

    return inverse_lbs_fwd


@functools.cache
def inverse_lbs_backward(dtype, n_bones: int, points: bool, weights: bool, bones: bool):
    """Inverse-LBS backward (see the module docstring), computing the gradients for ``points``,
    ``weights`` and ``bones`` (rotations and translations) that are asked for."""
    st = skinning_types(dtype)
    g, vec3, mat33 = st.grid, st.vec3, st.mat33
    NB, POINTS, WEIGHTS, BONES = n_bones, points, weights, bones

    @wp.kernel(enable_backward=False, module="unique", module_options=OPTIONS)
    def inverse_lbs_bwd(
        i0: int,
        points: wp.array(dtype=vec3),
        warp: st.Warp,
        out_x: wp.array(dtype=vec3),
        out_fg: wp.array(dtype=dtype),
        grad_x: wp.array(dtype=vec3),
        grad_fg: wp.array(dtype=dtype),
        grad_points: wp.array(dtype=vec3),
        grad_weights: wp.array4d(dtype=dtype),
        grad_rot: wp.array(dtype=mat33),
        grad_trans: wp.array(dtype=vec3),
    ):
        i = wp.tid() + i0
        x = points[i]
        # The forward outputs give the weighted sum back: acc = x_c * max(s, eps).
        s = out_fg[i]
        ms = wp.max(s, warp.eps)
        gacc = grad_x[i] / ms
        gs = grad_fg[i]
        if s > warp.eps:
            gs -= wp.dot(grad_x[i], out_x[i]) / ms
        gp = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for b in range(NB):
            y = warp.rot[b] * x + warp.trans[b]
            ok, base, frac = g.locate(y, warp.frame)
            if ok:
                w, gfrac = g.value_and_grad(g.corners4(warp.weights, b, base), frac)
                gw = wp.dot(gacc, y) + gs
                if wp.static(WEIGHTS):
                    g.scatter4(grad_weights, b, base, g.corner_weights(frac), gw)
                if wp.static(POINTS or BONES):
                    gy = w * gacc + gw * g.frac_to_world(gfrac, warp.frame)
                    if wp.static(BONES):
                        wp.atomic_add(grad_rot, b, wp.outer(gy, x))
                        wp.atomic_add(grad_trans, b, gy)
                    if wp.static(POINTS):
                        gp += wp.transpose(warp.rot[b]) * gy
        if wp.static(POINTS):
            grad_points[i] = gp

    return inverse_lbs_bwd


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
