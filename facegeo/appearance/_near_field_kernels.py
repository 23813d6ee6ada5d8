"""Compiled (numba) kernels of the near-field steps of :mod:`facegeo.appearance._near_field`.

One reflectance function per iteration of a ``prange`` loop; per function, one loop over its
lights computes what the numpy reference builds as ``(n, L, K)`` temporaries (the numpy path
is 2.5× the whole distant fit's CPU time at 512 lights):

* :func:`distant_equivalent_grid` — :func:`_near_field.distant_equivalent` on the light-stage
  grid: the node falloffs, the sphere point along each stage direction, its grid coordinate
  and the bilinear interpolation of ``R / a`` (and of the mask) of
  :func:`facegeo.appearance._skin_resynth.interpolate_on_lights`;
* :func:`separate_measured_kernel` — :func:`_near_field.separate_measured`'s Eq. 6 per sample
  at the light's true direction and the colour-space separation of §4.2
  (:func:`facegeo.appearance._skin_model.separate_colour`).

Same formulas in the same order as the numpy reference, which they are tested against
(``tests/test_skin_near_field.py``). Cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_S = 1.0 / math.sqrt(3.0)  # a component of S_WHITE
_TWO_PI = 2.0 * math.pi
_TINY = 1e-30  # _skin_model._TINY


@njit(cache=True, parallel=True)
def distant_equivalent_grid(R, mask, offsets, radius, dirs, nt, npf, out, mout):
    """``out[t, l] = Σ_k w_k R[t, q_k] / a_t(q_k)`` at the sphere point seen from point t along
    ``dirs[l]`` (bilinear on the (nt, npf) grid); ``mout[t, l]`` = any tap with weight > 0 is
    masked (``mask`` may be (0, 0): no mask)."""
    N, L, C = R.shape
    r2 = radius * radius
    has_mask = mask.shape[0] > 0
    for t in prange(N):
        dx, dy, dz = offsets[t, 0], offsets[t, 1], offsets[t, 2]
        dd = dx * dx + dy * dy + dz * dz
        inv_a = np.empty(L)
        for q in range(L):  # 1 / falloff of every node: |r ω_q − δ|² / r²
            x = radius * dirs[q, 0] - dx
            y = radius * dirs[q, 1] - dy
            z = radius * dirs[q, 2] - dz
            inv_a[q] = (x * x + y * y + z * z) / r2
        for l in range(L):
            ux, uy, uz = dirs[l, 0], dirs[l, 1], dirs[l, 2]
            du = dx * ux + dy * uy + dz * uz
            disc = du * du - dd + r2
            tt = -du + math.sqrt(disc if disc > 0.0 else 0.0)
            sx, sy, sz = dx + tt * ux, dy + tt * uy, dz + tt * uz
            nrm = math.sqrt(sx * sx + sy * sy + sz * sz)
            if nrm > _TINY:
                sx, sy, sz = sx / nrm, sy / nrm, sz / nrm
            else:
                sx, sy, sz = 0.0, 0.0, 1.0
            theta = math.atan2(sx, sz) % _TWO_PI
            phi = math.acos(min(1.0, max(-1.0, sy)))
            fi_ = theta * nt / _TWO_PI - 0.5
            fj_ = phi * npf / math.pi - 0.5
            i0 = math.floor(fi_)
            j0 = math.floor(fj_)
            fi = fi_ - i0
            fj = fj_ - j0
            ia = int(i0) % nt
            ib = (int(i0) + 1) % nt
            ja = min(max(int(j0), 0), npf - 1)
            jb = min(max(int(j0) + 1, 0), npf - 1)
            qs = (ja * nt + ia, ja * nt + ib, jb * nt + ia, jb * nt + ib)
            ws = ((1.0 - fj) * (1.0 - fi), (1.0 - fj) * fi, fj * (1.0 - fi), fj * fi)
            m = False
            for c in range(C):
                acc = 0.0
                for k in range(4):
                    acc += ws[k] * (R[t, qs[k], c] * inv_a[qs[k]])
                out[t, l, c] = acc
            if has_mask:
                for k in range(4):
                    if ws[k] > 0.0 and mask[t, qs[k]]:
                        m = True
                mout[t, l] = m


@njit(cache=True, parallel=True)
def separate_measured_kernel(R, E, offsets, radius, dirs, normal, view, d0, a0, a1, valid,
                             mask, singular_sin2, out):
    """D of the measured samples (white-balanced Eq. 6 at each light's true direction, then
    ``S = max(μ_s, 0) s``, ``D = R − S``, times E); ``D = R`` for invalid functions and at a
    singular matrix; ``D = 0`` at masked samples (``mask`` may be (0, 0))."""
    N, L, C = R.shape
    has_mask = mask.shape[0] > 0
    for t in prange(N):
        dx, dy, dz = offsets[t, 0], offsets[t, 1], offsets[t, 2]
        nx, ny, nz = normal[t, 0], normal[t, 1], normal[t, 2]
        nv = nx * view[t, 0] + ny * view[t, 1] + nz * view[t, 2]
        cr = min(1.0, max(0.0, nv))
        for l in range(L):
            if has_mask and mask[t, l]:
                for c in range(C):
                    out[t, l, c] = 0.0
                continue
            if not valid[t]:
                for c in range(C):
                    out[t, l, c] = R[t, l, c]
                continue
            x = radius * dirs[l, 0] - dx
            y = radius * dirs[l, 1] - dy
            z = radius * dirs[l, 2] - dz
            inv = 1.0 / math.sqrt(x * x + y * y + z * z)
            nl = (nx * x + ny * y + nz * z) * inv
            xx = min(1.0, max(0.0, nl)) * cr
            f = a0[t] * xx + a1[t] * (1.0 - xx)  # Eq. 7
            # Eq. 6: d = normalize(d_0 + f (d_0 − s))
            cx = d0[t, 0] + f * (d0[t, 0] - _S)
            cy = d0[t, 1] + f * (d0[t, 1] - _S)
            cz = d0[t, 2] + f * (d0[t, 2] - _S)
            cn = math.sqrt(cx * cx + cy * cy + cz * cz)
            if cn > _TINY:
                cx, cy, cz = cx / cn, cy / cn, cz / cn
            else:
                cx, cy, cz = _S, _S, _S
            rx, ry, rz = R[t, l, 0] / E[l, 0], R[t, l, 1] / E[l, 1], R[t, l, 2] / E[l, 2]
            ds = (cx + cy + cz) * _S
            det = 1.0 - ds * ds
            if det < singular_sin2:
                for c in range(C):
                    out[t, l, c] = R[t, l, c]
                continue
            rd = rx * cx + ry * cy + rz * cz
            rs = (rx + ry + rz) * _S
            mu_s = (rs - rd * ds) / det
            sv = (mu_s if mu_s > 0.0 else 0.0) * _S
            out[t, l, 0] = (rx - sv) * E[l, 0]
            out[t, l, 1] = (ry - sv) * E[l, 1]
            out[t, l, 2] = (rz - sv) * E[l, 2]
