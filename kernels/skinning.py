"""Warp kernels for linear blend skinning in both directions.

* ``inverse_lbs``: HumanNeRF's observation -> canonical warp. For each bone ``b`` the point is moved
  by that bone's observation->canonical transform, ``y_b = R_b x + t_b``, the bone's weight is read
  from a canonical motion-weight volume at ``y_b``, and
  ``x_c = sum_b w_b y_b / max(sum_b w_b, eps)``; ``fg = sum_b w_b`` is the foreground likelihood.
  The bone count is a compile-time constant of each kernel instance.
* ``forward_lbs``: mesh vertices, canonical -> posed, with sparse per-vertex bone weights.

Adjoints are hand-written, so only the gradients asked for are computed.
"""

import functools
from types import SimpleNamespace

import warp as wp

from .grid import grid_funcs


@functools.cache
def inverse_lbs_kernels(dtype, n_bones: int) -> SimpleNamespace:
    """Inverse-LBS kernels for ``n_bones`` bones (1..128) and scalar type ``dtype``."""
    if not 1 <= n_bones <= 128:
        raise ValueError(f"n_bones must be in 1..128, got {n_bones}")
    g = grid_funcs(dtype)
    vec3 = g.vec3
    mat33 = wp.types.matrix((3, 3), dtype)
    NB = n_bones

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def inverse_lbs_fwd(
        p0: int,
        points: wp.array(dtype=vec3),
        rot: wp.array(dtype=mat33),
        trans: wp.array(dtype=vec3),
        weights: wp.array4d(dtype=dtype),
        wmin: vec3,
        wscale: vec3,
        wres: wp.vec3i,
        eps: dtype,
        out_x: wp.array(dtype=vec3),
        out_fg: wp.array(dtype=dtype),
    ):
        i = wp.tid() + p0
        x = points[i]
        acc = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        s = dtype(0.0)
        for b in range(NB):
            y = rot[b] * x + trans[b]
            ok, base, frac = g.locate(y, wmin, wscale, wres)
            if ok:
                w = g.lerp4(weights, b, base, g.corner_weights(frac))
                acc += w * y
                s += w
        out_x[i] = acc / wp.max(s, eps)
        out_fg[i] = s

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def inverse_lbs_bwd(
        p0: int,
        points: wp.array(dtype=vec3),
        rot: wp.array(dtype=mat33),
        trans: wp.array(dtype=vec3),
        weights: wp.array4d(dtype=dtype),
        wmin: vec3,
        wscale: vec3,
        wres: wp.vec3i,
        eps: dtype,
        out_x: wp.array(dtype=vec3),
        out_fg: wp.array(dtype=dtype),
        grad_x: wp.array(dtype=vec3),
        grad_fg: wp.array(dtype=dtype),
        need_points: int,
        need_weights: int,
        need_bones: int,
        grad_points: wp.array(dtype=vec3),
        grad_weights: wp.array4d(dtype=dtype),
        grad_rot: wp.array(dtype=mat33),
        grad_trans: wp.array(dtype=vec3),
    ):
        i = wp.tid() + p0
        x = points[i]
        # The forward outputs give the weighted sum back: acc = x_c * max(s, eps).
        s = out_fg[i]
        ms = wp.max(s, eps)
        gacc = grad_x[i] / ms
        gs = grad_fg[i]
        if s > eps:
            gs -= wp.dot(grad_x[i], out_x[i]) / ms
        gp = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for b in range(NB):
            y = rot[b] * x + trans[b]
            ok, base, frac = g.locate(y, wmin, wscale, wres)
            if ok:
                w, gfrac = g.value_and_grad(g.corners4(weights, b, base), frac)
                gw = wp.dot(gacc, y) + gs
                if need_weights != 0:
                    g.scatter4(grad_weights, b, base, g.corner_weights(frac), gw)
                if need_points != 0 or need_bones != 0:
                    gy = w * gacc + gw * g.frac_to_world(gfrac, wscale)
                    if need_bones != 0:
                        wp.atomic_add(grad_rot, b, wp.outer(gy, x))
                        wp.atomic_add(grad_trans, b, gy)
                    if need_points != 0:
                        gp += wp.transpose(rot[b]) * gy
        if need_points != 0:
            grad_points[i] = gp

    return SimpleNamespace(vec3=vec3, mat33=mat33, fwd=inverse_lbs_fwd, bwd=inverse_lbs_bwd)


@functools.cache
def forward_lbs_kernels(dtype) -> SimpleNamespace:
    """Forward LBS of vertices with sparse (V, K) bone indices and weights."""
    vec3 = wp.types.vector(3, dtype)
    mat33 = wp.types.matrix((3, 3), dtype)

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def forward_lbs_fwd(
        verts: wp.array(dtype=vec3),
        bone_idx: wp.array2d(dtype=wp.int32),
        bone_w: wp.array2d(dtype=dtype),
        rot: wp.array(dtype=mat33),
        trans: wp.array(dtype=vec3),
        out: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        x = verts[i]
        acc = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for k in range(bone_idx.shape[1]):
            w = bone_w[i, k]
            if w != dtype(0.0):
                b = int(bone_idx[i, k])
                acc += w * (rot[b] * x + trans[b])
        out[i] = acc

    @wp.kernel(enable_backward=False, module="unique", module_options={"optimization_level": 3})
    def forward_lbs_bwd(
        verts: wp.array(dtype=vec3),
        bone_idx: wp.array2d(dtype=wp.int32),
        bone_w: wp.array2d(dtype=dtype),
        rot: wp.array(dtype=mat33),
        trans: wp.array(dtype=vec3),
        grad_out: wp.array(dtype=vec3),
        need_verts: int,
        need_bones: int,
        need_weights: int,
        grad_verts: wp.array(dtype=vec3),
        grad_rot: wp.array(dtype=mat33),
        grad_trans: wp.array(dtype=vec3),
        grad_w: wp.array2d(dtype=dtype),
    ):
        i = wp.tid()
        x = verts[i]
        go = grad_out[i]
        gx = vec3(dtype(0.0), dtype(0.0), dtype(0.0))
        for k in range(bone_idx.shape[1]):
            w = bone_w[i, k]
            b = int(bone_idx[i, k])
            if need_weights != 0:
                grad_w[i, k] = wp.dot(go, rot[b] * x + trans[b])
            if w != dtype(0.0):
                if need_verts != 0:
                    gx += w * (wp.transpose(rot[b]) * go)
                if need_bones != 0:
                    wp.atomic_add(grad_rot, b, w * wp.outer(go, x))
                    wp.atomic_add(grad_trans, b, w * go)
        if need_verts != 0:
            grad_verts[i] = gx

    return SimpleNamespace(vec3=vec3, mat33=mat33, fwd=forward_lbs_fwd, bwd=forward_lbs_bwd)
