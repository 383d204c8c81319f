"""The fast engine's primitives: the EKF's steps, the motion models' Jacobians and the ANFIS as
plain numeric code, and the families' rules registered with numba. `engines/loop.py` runs them
(one loop, a module per family under `engines/families/`); the banks, swvb, als and kalmannet
have kernels of their own on them (`kernels_bank.py`, `kernels_swvb.py`, `kernels_als.py`,
`kernels_kalmannet.py`).

Every function here is a module-level function on plain floats, tuples of floats and small
float64 arrays, so that numba can compile it (`numba.njit(cache=True)`: the compiled code is
cached on disk next to this file, which needs module-level functions) and so that the very same
code runs as plain Python when numba is not installed. `JIT` says which of the two this module
is; `pure_module()` loads a second, never-compiled copy of it (for tests and for debugging).
Set the environment variable ANFEKF_FAST_JIT=0 to keep numba off even when it is installed.

The arithmetic follows the reference engine (filterpy's `ExtendedKalmanFilter` driven by
`RobotEKF`, `ANFEKF` and `anfis`) operation by operation: the same products in the same order,
the same Joseph-form update and symmetrisation, the same sequential sums where numpy sums
sequentially (row sums of the ANFIS memberships, the window mean). What cannot be copied bit for
bit is BLAS's order (and fused multiply-adds) inside numpy's small matrix products and numpy's
vectorised `exp`: those differ by a rounding in the last place, which is why the two engines
agree to round-off (about 1e-13 on the paper scenarios) rather than bit for bit.

Matrices are tuples in row-major order: P = (p00, p01, p02, p10, ..., p22), H = (h00, h01, h10,
h11) (its third column is always (0, -1)), R and Qu = (r00, r01, r10, r11). P is carried in full,
not as its upper triangle, because filterpy's predicted P is symmetric only up to round-off.
"""

from __future__ import annotations

import importlib.util
import math
import sys

import numpy as np

from ..compiled import NJIT_OPTIONS, numba_njit
from ..filters import adaptive as _adaptive
from ..filters import akhlaghi as _akhlaghi
from ..filters import cm_scale as _cm_scale
from ..filters import fading as _fading
from ..filters import iae as _iae
from ..filters import sage_husa as _sage_husa
from ..filters import vb as _vb
from ..models import motion_terms as _motion_terms

# numba.njit, or None when numba is missing, switched off (compiled.numba_njit) or this is the
# pure copy
_NJIT = None if globals().get("_PURE", False) else numba_njit()
JIT: bool = _NJIT is not None  # True: the kernels below are numba-compiled


def maybe_njit(fn):
    """`fn` compiled with compiled.NJIT_OPTIONS when numba is in use, else the function itself."""
    if _NJIT is None:
        return fn
    return _NJIT(**NJIT_OPTIONS)(fn)


def jitable(*rules):
    """`rules`, functions as written in the filters' modules, registered with numba when it is in
    use (compiled code then calls them, compiled as its callees); returned as given."""
    if _NJIT is not None:
        from numba.extending import register_jitable

        for rule in rules:
            register_jitable(rule)
    return rules


def pure_copy(name: str, path: str):
    """A fresh copy of the kernel module `name` (file `path`) whose kernels are plain Python,
    whatever is installed (kept in sys.modules as `name`_pure)."""
    pure = name + "_pure"
    if pure in sys.modules:
        return sys.modules[pure]
    spec = importlib.util.spec_from_file_location(pure, path)
    mod = importlib.util.module_from_spec(spec)
    mod._PURE = True  # read (for `_NJIT`, and by kernels_als) while the copy executes
    spec.loader.exec_module(mod)
    sys.modules[pure] = mod
    return mod


def pure_module():
    """A fresh copy of this module whose kernels are plain Python, whatever is installed."""
    return pure_copy(__name__, __file__)


PI = math.pi
TWO_PI = 2.0 * math.pi
U_CLIP = 1e100  # anfis._U_CLIP: inputs clipped so (u - m)^2 / delta^2 cannot overflow
MIN_WIDTH = 1e-3  # anfis.sgd_step's floor on the membership widths

# Layout of one ANFIS parameter row (27 floats): centres m (2 x 5, row-major), widths delta
# (2 x 5), singletons w (7). A gradient has the same layout.
N_ANFIS = 27
M0, D0, W0 = 0, 10, 20


# ---------------------------------------------------------------------------------------------
# Scalars


@maybe_njit
def wrap(a):
    """models.angles.wrap_scalar: angle to (-pi, pi] (Python's float modulo). The modulo is
    skipped where it is the identity (0 <= -a + pi < 2 pi, the usual case): the same bits."""
    y = -a + PI
    if not (0.0 <= y < TWO_PI):
        y = y % TWO_PI
    return -(y - PI)


@maybe_njit
def clip_nan(v, lo, hi):
    """np.clip on one value: min(max(v, lo), hi), NaN stays NaN."""
    if v != v:
        return v
    if v < lo:
        v = lo
    if v > hi:
        v = hi
    return v


@maybe_njit
def min_nan(a, b):
    """np.minimum on two values (NaN propagates)."""
    if a != a or b != b:
        return a + b
    return a if a <= b else b


# ---------------------------------------------------------------------------------------------
# EKF: predict, innovation, gate, Joseph update, health


# The motion models (models.bicycle, models.unicycle), a kernel argument, and one step of each:
# models.motion_terms, the formulas the filterpy engine's models use, compiled here
MOTION_BICYCLE = _motion_terms.MOTION_BICYCLE
MOTION_UNICYCLE = _motion_terms.MOTION_UNICYCLE
step_terms = maybe_njit(_motion_terms.step_terms)
jacobians_at = maybe_njit(_motion_terms.jacobians_at)


@maybe_njit
def jacobians(x2, u0, u1, dt, motion, B):
    """F and G of one step of `motion` from heading x2 with controls (u0, u1) over dt:
    (f02, f12, G) with F = [[1, 0, f02], [0, 1, f12], [0, 0, 1]] and G = (g00, g01, g10, g11,
    g20, g21) row-major (models.motion_terms)."""
    return jacobians_at(x2, step_terms(u0, u1, dt, motion, B))


@maybe_njit
def noise_scale(dt, motion, T0):
    """What `motion`'s Q multiplies G Qu G^T by: 1 (bicycle), T0 / dt (unicycle; 0 for a step
    of no length, as Unicycle.Q)."""
    if motion == MOTION_UNICYCLE:
        return T0 / dt if dt > 0.0 else 0.0
    return 1.0


@maybe_njit
def predict(x, P, u0, u1, dt, motion, B, T0, Qu):
    """RobotEKF.predict with `motion`'s model: F and G at (x, u), x- = f(x, u),
    P- = F P F^T + Q (eqs. 19-21). Returns (x-, P-, Q): Q = G Qu G^T (bicycle, eq. 20) or
    (T0 / dt) G Qu G^T (unicycle, 0 for dt <= 0)."""
    f02, f12, G = jacobians(x[2], u0, u1, dt, motion, B)
    return predict_with(x, P, f02, f12, G, u0, u1, dt, motion, B, T0, Qu)


@maybe_njit
def predict_with(x, P, f02, f12, G, u0, u1, dt, motion, B, T0, Qu):
    """`predict` given the step's Jacobians (f02, f12, G) = jacobians(x[2], ...): a kernel that
    needs them for its own bookkeeping too (`interval_step`) computes them once."""
    if motion == MOTION_UNICYCLE:
        return predict_from(x, P, f02, f12, G, u1 * dt, noise_scale(dt, motion, T0), Qu)
    return predict_from(x, P, f02, f12, G, dt * u0 * math.sin(u1) / B, 1.0, Qu)


@maybe_njit
def predict_from(x, P, f02, f12, G, dh, c, Qu):
    """`predict_with` given the heading's step dh (x2- = wrap(x2 + dh)) and the factor c on
    G Qu G^T (noise_scale; 1.0 leaves Q as it is): a bank computes both once per step."""
    x0, x1, x2 = x
    q00, q01, q10, q11 = Qu
    g00, g01, g10, g11, g20, g21 = G
    # Q = (G Qu) G^T
    a00 = g00 * q00 + g01 * q10
    a01 = g00 * q01 + g01 * q11
    a10 = g10 * q00 + g11 * q10
    a11 = g10 * q01 + g11 * q11
    a20 = g20 * q00 + g21 * q10
    a21 = g20 * q01 + g21 * q11
    Q = (
        a00 * g00 + a01 * g01, a00 * g10 + a01 * g11, a00 * g20 + a01 * g21,
        a10 * g00 + a11 * g01, a10 * g10 + a11 * g11, a10 * g20 + a11 * g21,
        a20 * g00 + a21 * g01, a20 * g10 + a21 * g11, a20 * g20 + a21 * g21,
    )  # fmt: skip
    if c != 1.0:  # the unicycle's T0 / dt (Unicycle.Q); 1.0 * q is q, so the test is exact
        Q = (
            c * Q[0], c * Q[1], c * Q[2], c * Q[3], c * Q[4], c * Q[5], c * Q[6], c * Q[7],
            c * Q[8],
        )  # fmt: skip
    # x- = f(x, u) (bicycle.f, Unicycle.f)
    xn = (x0 + f12, x1 - f02, wrap(x2 + dh))
    return xn, propagate(P, f02, f12, Q), Q


@maybe_njit
def propagate(P, f02, f12, Q):
    """(F P) F^T + Q for the bicycle's F = [[1, 0, f02], [0, 1, f12], [0, 0, 1]], its zeros and
    ones taken as they are (P, Q row-major 9-tuples)."""
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = P
    b00 = p00 + f02 * p20
    b01 = p01 + f02 * p21
    b02 = p02 + f02 * p22
    b10 = p10 + f12 * p20
    b11 = p11 + f12 * p21
    b12 = p12 + f12 * p22
    return (
        (b00 + b02 * f02) + Q[0], (b01 + b02 * f12) + Q[1], b02 + Q[2],
        (b10 + b12 * f02) + Q[3], (b11 + b12 * f12) + Q[4], b12 + Q[5],
        (p20 + p22 * f02) + Q[6], (p21 + p22 * f12) + Q[7], p22 + Q[8],
    )  # fmt: skip


@maybe_njit
def innovation(x, P, lx, ly, z0, z1):
    """RobotEKF.innovation: H (eq. 25), z_hat = h(x-) (eq. 22), nu (eq. 23, bearing wrapped)
    and H P- H^T, all at x-."""
    x0, x1, x2 = x
    dx = lx - x0
    dy = ly - x1
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    h00 = -dx / r
    h01 = -dy / r
    h10 = dy / q
    h11 = -dx / q
    zh0 = math.hypot(dx, dy)
    zh1 = wrap(math.atan2(dy, dx) - x2)
    nu0 = z0 - zh0
    nu1 = wrap(z1 - zh1)
    H = (h00, h01, h10, h11)
    return H, (zh0, zh1), (nu0, nu1), hph(H, P)


@maybe_njit
def hph(H, P):
    """H P H^T (row-major 4-tuple) for the H of `innovation` (third column (0, -1))."""
    h00, h01, h10, h11 = H
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = P
    # H P (2 x 3); H's third column is (0, -1)
    c00 = h00 * p00 + h01 * p10
    c01 = h00 * p01 + h01 * p11
    c02 = h00 * p02 + h01 * p12
    c10 = h10 * p00 + h11 * p10 - p20
    c11 = h10 * p01 + h11 * p11 - p21
    c12 = h10 * p02 + h11 * p12 - p22
    HPHt = (
        c00 * h00 + c01 * h01, c00 * h10 + c01 * h11 - c02,
        c10 * h00 + c11 * h01, c10 * h10 + c11 * h11 - c12,
    )  # fmt: skip
    return HPHt


@maybe_njit
def lu2(s00, s01, s10, s11):
    """LAPACK's LU with partial pivoting of a 2 x 2 matrix, as numpy and scipy run it (the
    multiplier is s10 * (1 / s00)): (swapped, u00, u01, l10, u11). The matrix is singular for
    LAPACK (numpy's LinAlgError) exactly when u00 or u11 is 0."""
    swapped = abs(s10) > abs(s00)
    if swapped:
        s00, s01, s10, s11 = s10, s11, s00, s01
    l10 = s10 * (1.0 / s00) if s00 != 0.0 else 0.0
    return swapped, s00, s01, l10, s11 - l10 * s01


@maybe_njit
def nis(HPHt, R, nu0, nu1):
    """nu^T S^-1 nu with S = H P H^T + R, by the LU solve of np.linalg.solve. Returns
    (ok, nis); ok is False for a matrix LAPACK finds singular (numpy's LinAlgError)."""
    swapped, u00, u01, l10, u11 = lu2(
        HPHt[0] + R[0], HPHt[1] + R[1], HPHt[2] + R[2], HPHt[3] + R[3]
    )
    if u00 == 0.0 or u11 == 0.0:
        return False, math.nan
    b0, b1 = (nu1, nu0) if swapped else (nu0, nu1)
    v1 = (b1 - l10 * b0) / u11
    v0 = (b0 - u01 * v1) / u00
    return True, nu0 * v0 + nu1 * v1


@maybe_njit
def feeds_adaptation(HPHt, R, nu, from_all, gate, has_gate):
    """AdaptiveEKF.feeds_adaptation: (ok, whether this landmark feeds adaptation), every
    landmark with adapt_from all or no gate, else one the gate would accept (its NIS with R);
    ok is False for a matrix LAPACK finds singular (the filter diverged)."""
    if from_all or not has_gate:
        return True, True
    ok, v = nis(HPHt, R, nu[0], nu[1])
    if not ok:
        return False, False
    return True, v <= gate


@maybe_njit
def gain(P, H, R):
    """filterpy's gain K = P H^T S^-1, S = H P H^T + R, S^-1 as scipy.linalg.inv computes it.
    Returns (ok, K) with K (3 x 2) row-major; ok is False for an exactly singular S."""
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = P
    h00, h01, h10, h11 = H
    r00, r01, r10, r11 = R
    # PHT = P H^T (3 x 2)
    t00 = p00 * h00 + p01 * h01
    t01 = p00 * h10 + p01 * h11 - p02
    t10 = p10 * h00 + p11 * h01
    t11 = p10 * h10 + p11 * h11 - p12
    t20 = p20 * h00 + p21 * h01
    t21 = p20 * h10 + p21 * h11 - p22
    # S = H PHT + R
    s00 = (h00 * t00 + h01 * t10) + r00
    s01 = (h00 * t01 + h01 * t11) + r01
    s10 = (h10 * t00 + h11 * t10 - t20) + r10
    s11 = (h10 * t01 + h11 * t11 - t21) + r11
    # S^-1 as scipy.linalg.inv computes it: LU (getrf), then the inverse of U and the solve
    # with L (getri)
    swapped, u00, u01, l10, u11 = lu2(s00, s01, s10, s11)
    if u00 == 0.0 or u11 == 0.0:
        return False, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    v00 = 1.0 / u00
    v11 = 1.0 / u11
    v01 = (v00 * u01) * (-v11)
    i00 = v00 - v01 * l10
    i01 = v01
    i10 = 0.0 - v11 * l10
    i11 = v11
    if swapped:  # column interchange
        i00, i01, i10, i11 = i01, i00, i11, i10
    # K = PHT S^-1 (3 x 2)
    k00 = t00 * i00 + t01 * i10
    k01 = t00 * i01 + t01 * i11
    k10 = t10 * i00 + t11 * i10
    k11 = t10 * i01 + t11 * i11
    k20 = t20 * i00 + t21 * i10
    k21 = t20 * i01 + t21 * i11
    return True, (k00, k01, k10, k11, k20, k21)


@maybe_njit
def correct(x, P, H, zh, z0, z1, R):
    """RobotEKF.correct: filterpy's update with the H and z_hat of the innovation, Joseph form
    P = (I - K H) P (I - K H)^T + K R K^T, then heading wrapped and P symmetrised.
    Returns (ok, x+, P+); ok is False for an exactly singular S (scipy's inv raises)."""
    x0, x1, x2 = x
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = P
    h00, h01, h10, h11 = H
    r00, r01, r10, r11 = R
    ok, K = gain(P, H, R)
    if not ok:
        return False, x, P
    k00, k01, k10, k11, k20, k21 = K
    # y = residual_z(z, z_hat); x = x + K y
    y0 = z0 - zh[0]
    y1 = wrap(z1 - zh[1])
    x0 = x0 + (k00 * y0 + k01 * y1)
    x1 = x1 + (k10 * y0 + k11 * y1)
    x2 = x2 + (k20 * y0 + k21 * y1)
    # A = I - K H (3 x 3); H's third column is (0, -1)
    a00 = 1.0 - (k00 * h00 + k01 * h10)
    a01 = -(k00 * h01 + k01 * h11)
    a02 = k01
    a10 = -(k10 * h00 + k11 * h10)
    a11 = 1.0 - (k10 * h01 + k11 * h11)
    a12 = k11
    a20 = -(k20 * h00 + k21 * h10)
    a21 = -(k20 * h01 + k21 * h11)
    a22 = 1.0 + k21
    # M = A P
    m00 = a00 * p00 + a01 * p10 + a02 * p20
    m01 = a00 * p01 + a01 * p11 + a02 * p21
    m02 = a00 * p02 + a01 * p12 + a02 * p22
    m10 = a10 * p00 + a11 * p10 + a12 * p20
    m11 = a10 * p01 + a11 * p11 + a12 * p21
    m12 = a10 * p02 + a11 * p12 + a12 * p22
    m20 = a20 * p00 + a21 * p10 + a22 * p20
    m21 = a20 * p01 + a21 * p11 + a22 * p21
    m22 = a20 * p02 + a21 * p12 + a22 * p22
    # N = K R
    n00 = k00 * r00 + k01 * r10
    n01 = k00 * r01 + k01 * r11
    n10 = k10 * r00 + k11 * r10
    n11 = k10 * r01 + k11 * r11
    n20 = k20 * r00 + k21 * r10
    n21 = k20 * r01 + k21 * r11
    # P = M A^T + N K^T
    q00 = (m00 * a00 + m01 * a01 + m02 * a02) + (n00 * k00 + n01 * k01)
    q01 = (m00 * a10 + m01 * a11 + m02 * a12) + (n00 * k10 + n01 * k11)
    q02 = (m00 * a20 + m01 * a21 + m02 * a22) + (n00 * k20 + n01 * k21)
    q10 = (m10 * a00 + m11 * a01 + m12 * a02) + (n10 * k00 + n11 * k01)
    q11 = (m10 * a10 + m11 * a11 + m12 * a12) + (n10 * k10 + n11 * k11)
    q12 = (m10 * a20 + m11 * a21 + m12 * a22) + (n10 * k20 + n11 * k21)
    q20 = (m20 * a00 + m21 * a01 + m22 * a02) + (n20 * k00 + n21 * k01)
    q21 = (m20 * a10 + m21 * a11 + m22 * a12) + (n20 * k10 + n21 * k11)
    q22 = (m20 * a20 + m21 * a21 + m22 * a22) + (n20 * k20 + n21 * k21)
    # symmetrise: 0.5 * (P + P^T)
    s01 = 0.5 * (q01 + q10)
    s02 = 0.5 * (q02 + q20)
    s12 = 0.5 * (q12 + q21)
    Pn = (0.5 * (q00 + q00), s01, s02, s01, 0.5 * (q11 + q11), s12, s02, s12, 0.5 * (q22 + q22))
    return True, (x0, x1, wrap(x2)), Pn


@maybe_njit
def healthy(x, P, R, Qu):
    """filterpy_engine._healthy: x and P finite, P positive definite (numpy's Cholesky reads the
    lower triangle), the diagonals of R and Qu positive."""
    for v in x:
        if not math.isfinite(v):
            return False
    for v in P:
        if not math.isfinite(v):
            return False
    l00 = P[0]
    if not l00 > 0.0:
        return False
    l00 = math.sqrt(l00)
    l10 = P[3] / l00
    l20 = P[6] / l00
    d1 = P[4] - l10 * l10
    if not d1 > 0.0:
        return False
    l11 = math.sqrt(d1)
    l21 = (P[7] - l20 * l10) / l11
    d2 = P[8] - l20 * l20 - l21 * l21
    if not d2 > 0.0:
        return False
    return R[0] > 0.0 and R[3] > 0.0 and Qu[0] > 0.0 and Qu[3] > 0.0


# ---------------------------------------------------------------------------------------------
# ANFIS (filters.anfis) and the supervisor's steps (filters.anfekf.r_step, q_step)


@maybe_njit
def anfis_output_grad(prm, u0, u1, grad, ws):
    """anfis.output_and_gradient: the output o (eq. 38) and do/dW written into `grad` (27).

    `prm` is one parameter row (layout M0, D0, W0); `ws` is scratch (>= 40 floats): z at 0..9,
    the normalised memberships p (input 0) at 10..14 and q (input 1) at 15..19, W q at 20..24,
    W^T p at 25..29.
    """
    for i in range(2):
        u = u0 if i == 0 else u1
        if u > U_CLIP:
            u = U_CLIP
        elif u < -U_CLIP:
            u = -U_CLIP
        # log-memberships -z^2 and their maximum (np.max: NaN propagates)
        mx = -math.inf
        for j in range(5):
            k = 5 * i + j
            zz = (u - prm[M0 + k]) / prm[D0 + k]
            ws[k] = zz
            lg = -zz * zz
            ws[10 + k] = lg
            if lg != lg or mx != mx:
                mx = lg + mx
            elif lg > mx:
                mx = lg
        s = 0.0
        for j in range(5):
            k = 10 + 5 * i + j
            e = math.exp(ws[k] - mx)
            ws[k] = e
            s += e
        for j in range(5):
            k = 10 + 5 * i + j
            ws[k] = ws[k] / s
    # Singleton of rule (r, c): w[clip(8 - (r + c), 1, 7) - 1] (anfis.RULE_TABLE)
    o = 0.0
    for r in range(5):
        t = 0.0
        for c in range(5):
            t += prm[W0 + min(max(8 - r - c, 1), 7) - 1] * ws[15 + c]
        ws[20 + r] = t
        o += ws[10 + r] * t
    for c in range(5):
        t = 0.0
        for r in range(5):
            t += ws[10 + r] * prm[W0 + min(max(8 - r - c, 1), 7) - 1]
        ws[25 + c] = t
    # d o / d log(mu_ij), then through eq. 35 to the centres and widths
    for j in range(5):
        dl0 = ws[10 + j] * (ws[20 + j] - o)
        dm0 = dl0 * (2.0 * ws[j] / prm[D0 + j])
        grad[M0 + j] = dm0
        grad[D0 + j] = dm0 * ws[j]
        dl1 = ws[15 + j] * (ws[25 + j] - o)
        dm1 = dl1 * (2.0 * ws[5 + j] / prm[D0 + 5 + j])
        grad[M0 + 5 + j] = dm1
        grad[D0 + 5 + j] = dm1 * ws[5 + j]
    # do/dw_k: the normalised firing strengths p_r q_c of the rules that use singleton k
    for k in range(7):
        grad[W0 + k] = 0.0
    for r in range(5):
        for c in range(5):
            k = min(max(8 - r - c, 1), 7) - 1
            grad[W0 + k] += ws[10 + r] * ws[15 + c]
    return o


@maybe_njit
def clip_output(o, limit):
    """anfekf._clip: (o clipped to +-limit, whether it was inside)."""
    if -limit <= o <= limit:
        return o, True
    return math.copysign(limit, o), False


@maybe_njit
def sgd_step(prm, grad, k, eta_m, eta_d, eta_w):
    """anfis.sgd_step with the loss gradient k * do/dW (anfekf._scaled), in place."""
    for i in range(10):
        prm[M0 + i] = prm[M0 + i] - eta_m * (grad[M0 + i] * k)
    for i in range(10):
        v = prm[D0 + i] - eta_d * (grad[D0 + i] * k)
        # np.maximum(v, MIN_WIDTH): NaN propagates
        prm[D0 + i] = v if (v != v or v > MIN_WIDTH) else MIN_WIDTH
    for i in range(7):
        prm[W0 + i] = prm[W0 + i] - eta_w * (grad[W0 + i] * k)


@maybe_njit
def r_step(prm, u0, u1, R_ii, HPH_ii, C_ii, clip, learning, eta_m, eta_d, eta_w, grad, ws):
    """anfekf.r_step then ANFEKF._learn: R'_ii = R_ii exp(o) (eq. 33), and one steepest-descent
    step on E = e^2 / 2 with e = mismatch(H P H^T + R', C) unless o was clipped."""
    o_raw = anfis_output_grad(prm, u0, u1, grad, ws)
    o, inside = clip_output(o_raw, clip)
    R_new = R_ii * math.exp(o)
    S_new = HPH_ii + R_new
    e = (S_new - C_ii) / (S_new + C_ii)
    dE_do = e * 2.0 * C_ii / (S_new + C_ii) ** 2 * R_new
    if learning and inside:
        sgd_step(prm, grad, dE_do, eta_m, eta_d, eta_w)
    return R_new


@maybe_njit
def q_step(prm, u0, u1, S0, S1, C0, C1, dS0, dS1, clip, learning, eta_m, eta_d, eta_w, grad, ws):
    """anfekf.q_step then ANFEKF._learn: the scale e^o of Qu (eq. 44) and one steepest-descent
    step on E = (e_1^2 + e_2^2) / 2, S' = S + (e^o - 1) dS, unless o was clipped."""
    o_raw = anfis_output_grad(prm, u0, u1, grad, ws)
    o, inside = clip_output(o_raw, clip)
    scale = math.exp(o)
    Sn0 = S0 + (scale - 1.0) * dS0
    Sn1 = S1 + (scale - 1.0) * dS1
    e0 = (Sn0 - C0) / (Sn0 + C0)
    e1 = (Sn1 - C1) / (Sn1 + C1)
    t0 = e0 * 2.0 * C0 / (Sn0 + C0) ** 2 * scale * dS0
    t1 = e1 * 2.0 * C1 / (Sn1 + C1) ** 2 * scale * dS1
    dE_do = t0 + t1
    if learning and inside:
        sgd_step(prm, grad, dE_do, eta_m, eta_d, eta_w)
    return scale


@maybe_njit
def hqh_diag(H, Qi, HPH0, HPH1):
    """ANFEKF._adapt_Q's dS: the diagonal of H Q_interval H^T, capped at H P- H^T."""
    h0 = (H[0], H[1], 0.0)
    h1 = (H[2], H[3], -1.0)
    a0 = 0.0
    a1 = 0.0
    for j in range(3):
        for k in range(3):
            a0 += h0[j] * Qi[3 * j + k] * h0[k]
            a1 += h1[j] * Qi[3 * j + k] * h1[k]
    return min_nan(a0, HPH0), min_nan(a1, HPH1)


# ---------------------------------------------------------------------------------------------
# The rules of the adaptive families, as written in their modules (filters/*.py) and registered
# with numba so that compiled code calls them. numba's disk cache of a kernel is stamped with
# every source it reaches, these modules included (compiled.use_reached_sources_stamp; the
# loops' files are named by them), so an edited rule compiles the kernels that call it anew.

proportional_step, mean_mismatch = jitable(_cm_scale.proportional_step, _cm_scale.mean_mismatch)

# ---------------------------------------------------------------------------------------------
# The fading-factor EKF (filters.fading), its rule as written there

fading_factor, _ = jitable(_fading.fading_factor, _fading.fading_event)


# ---------------------------------------------------------------------------------------------
# What the adaptive families share (filters.adaptive): the bounds, the interval's process-noise
# accumulators A_v, A_g and the least-squares map of a state-space Q to Qu

if _NJIT is not None:
    from numba.extending import overload

    @overload(_adaptive.matmul)
    def _matmul_loop(A, B):
        """Compiled, the rules' A @ B is a plain loop (k ascending, as a dot product sums): for
        3 x 3 matrices BLAS's call costs more than the product."""

        if B.ndim == 1:  # a matrix times a vector

            def impl_vector(A, B):
                n, m = A.shape
                out = np.empty(n)
                for i in range(n):
                    t = 0.0
                    for k in range(m):
                        t += A[i, k] * B[k]
                    out[i] = t
                return out

            return impl_vector

        def impl(A, B):
            n, m = A.shape
            p = B.shape[1]
            out = np.empty((n, p))
            if n == 3 and m == 3 and p == 3:  # the rules' usual case, unrolled: the same sums
                for i in range(3):
                    a0, a1, a2 = A[i, 0], A[i, 1], A[i, 2]
                    out[i, 0] = 0.0 + a0 * B[0, 0] + a1 * B[1, 0] + a2 * B[2, 0]
                    out[i, 1] = 0.0 + a0 * B[0, 1] + a1 * B[1, 1] + a2 * B[2, 1]
                    out[i, 2] = 0.0 + a0 * B[0, 2] + a1 * B[1, 2] + a2 * B[2, 2]
                return out
            for i in range(n):
                for j in range(p):
                    t = 0.0
                    for k in range(m):
                        t += A[i, k] * B[k, j]
                    out[i, j] = t
            return out

        return impl

    @overload(_adaptive.outer)
    def _outer_loop(a, b):
        """Compiled, np.outer as a plain loop (numba's np.outer costs ten times as much)."""

        def impl(a, b):
            n = a.shape[0]
            p = b.shape[0]
            out = np.empty((n, p))
            for i in range(n):
                for j in range(p):
                    out[i, j] = a[i] * b[j]
            return out

        return impl

    @overload(_adaptive.trace_of_product)
    def _trace_of_product_loop(A, B):
        """Compiled, tr(A B) from the product's diagonal only: each diagonal entry summed as
        `matmul`'s loop sums it, then the entries in order as np.trace sums them."""

        def impl(A, B):
            n, m = A.shape
            t = 0.0
            for i in range(n):
                d = 0.0
                for k in range(m):
                    d += A[i, k] * B[k, i]
                t += d
            return t

        return impl

    @overload(_adaptive.inv)
    def _inv_loop(A):
        """Compiled, the rules' inverse is Gauss-Jordan elimination with partial pivoting in
        plain loops (LAPACK's call costs ten times the arithmetic of a 3 x 3); it raises
        LinAlgError where numba's np.linalg.inv does: a matrix with a value that is not finite,
        or an exactly singular one."""

        def impl(A):
            n = A.shape[0]
            a = np.empty((n, n))
            out = np.zeros((n, n))
            for i in range(n):
                out[i, i] = 1.0
                for j in range(n):
                    v = A[i, j]
                    if not math.isfinite(v):
                        raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
                    a[i, j] = v
            for c in range(n):
                p = c
                for r in range(c + 1, n):
                    if abs(a[r, c]) > abs(a[p, c]):
                        p = r
                if a[p, c] == 0.0:
                    raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
                if p != c:
                    for j in range(n):
                        a[c, j], a[p, j] = a[p, j], a[c, j]
                        out[c, j], out[p, j] = out[p, j], out[c, j]
                for r in range(n):
                    if r != c:
                        f = a[r, c] / a[c, c]
                        for j in range(n):
                            a[r, j] -= f * a[c, j]
                            out[r, j] -= f * out[c, j]
            for i in range(n):
                d = a[i, i]
                for j in range(n):
                    out[i, j] = out[i, j] / d
            return out

        return impl

    @overload(_adaptive.lstsq)
    def _lstsq_2x2(M, b):
        """Compiled, the 2 x 2 least squares in closed form, the solution LAPACK's SVD gives to
        round-off: singular values s1 >= s2 from the matrix's invariants; when s2 <= LSTSQ_RCOND
        s1 (numerically rank one) the least-norm solution M^T b / ||M||_F^2, else M^-1 b by
        LAPACK's LU (`lu2`). A value of M that is not finite raises LinAlgError, as numpy."""
        rcond = _adaptive.LSTSQ_RCOND

        def impl(M, b):
            m00, m01, m10, m11 = M[0, 0], M[0, 1], M[1, 0], M[1, 1]
            if not (
                math.isfinite(m00) and math.isfinite(m01)
                and math.isfinite(m10) and math.isfinite(m11)
            ):  # fmt: skip
                raise np.linalg.LinAlgError("SVD did not converge in Linear Least Squares")
            b0, b1 = b[0], b[1]
            out = np.zeros(2)
            fro2 = m00 * m00 + m01 * m01 + m10 * m10 + m11 * m11
            if fro2 == 0.0:
                return out  # every singular value is 0: the least-norm solution is 0
            # s1 = (|(m00 + m11, m10 - m01)| + |(m00 - m11, m10 + m01)|) / 2, s1 s2 = |det M|
            s1 = 0.5 * (math.hypot(m00 + m11, m10 - m01) + math.hypot(m00 - m11, m10 + m01))
            s2 = abs(m00 * m11 - m01 * m10) / s1
            if s2 <= rcond * s1:
                out[0] = (m00 * b0 + m10 * b1) / fro2
                out[1] = (m01 * b0 + m11 * b1) / fro2
                return out
            swapped, u00, u01, l10, u11 = lu2(m00, m01, m10, m11)
            c0, c1 = (b1, b0) if swapped else (b0, b1)
            out[1] = (c1 - l10 * c0) / u11
            out[0] = (c0 - u01 * out[1]) / u00
            return out

        return impl


clip_to_bounds, qu_least_squares = jitable(_adaptive.clip_to_bounds, _adaptive.qu_least_squares)
matmul = _adaptive.matmul
outer = _adaptive.outer
trace_of_product = _adaptive.trace_of_product
inv = _adaptive.inv
lstsq = _adaptive.lstsq
next_beta, fading_mean, r_sample, q_sample = jitable(
    _sage_husa.next_beta, _sage_husa.fading_mean, _sage_husa.r_sample, _sage_husa.q_sample
)


@maybe_njit
def as_matrix(P):
    """A row-major 3 x 3 tuple as an array."""
    A = np.empty((3, 3))
    for i in range(9):
        A[i // 3, i % 3] = P[i]
    return A


ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
EYE9 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@maybe_njit
def interval_step(A_v, A_g, F_scan, f02, f12, G, c):
    """AdaptiveEKF.predict's accumulators (filters.adaptive.propagate_interval) at a predict
    whose Jacobians are (f02, f12, G) = jacobians(...) (computed once, shared with
    `predict_with`) and whose Q is c G Qu G^T (c = noise_scale), on row-major 9-tuples (no
    arrays: this runs at every step). A <- F A F^T + c G e e^T G^T is the EKF's covariance
    predict with Qu = e e^T, `propagate` above, and F_scan <- F F_scan; the same products, bit
    for bit, as the rule's loops over F's zeros and ones (exact for finite values)."""
    g00, g01, g10, g11, g20, g21 = G
    # the model's Q of a unit noise e: c G e e^T G^T (c = 1 for the bicycle: exact)
    Q_v = (
        c * (g00 * g00), c * (g00 * g10), c * (g00 * g20),
        c * (g10 * g00), c * (g10 * g10), c * (g10 * g20),
        c * (g20 * g00), c * (g20 * g10), c * (g20 * g20),
    )  # fmt: skip
    Q_g = (
        c * (g01 * g01), c * (g01 * g11), c * (g01 * g21),
        c * (g11 * g01), c * (g11 * g11), c * (g11 * g21),
        c * (g21 * g01), c * (g21 * g11), c * (g21 * g21),
    )  # fmt: skip
    s00, s01, s02, s10, s11, s12, s20, s21, s22 = F_scan
    F_scan = (
        s00 + f02 * s20, s01 + f02 * s21, s02 + f02 * s22,
        s10 + f12 * s20, s11 + f12 * s21, s12 + f12 * s22,
        s20, s21, s22,
    )  # fmt: skip
    return propagate(A_v, f02, f12, Q_v), propagate(A_g, f02, f12, Q_g), F_scan


@maybe_njit
def qu_estimate(Q_hat, A_v, A_g, P):
    """AdaptiveEKF.qu_estimate: (ok, (qv, qg)) not clipped, A_v, A_g and P row-major 9-tuples;
    ok is False when P is singular or not finite (LinAlgError: the filter diverged)."""
    try:
        W = inv(as_matrix(P))
        q = qu_least_squares(Q_hat, as_matrix(A_v), as_matrix(A_g), W)
    except Exception:  # numba catches no narrower class
        return False, (0.0, 0.0)
    return True, (q[0], q[1])


# What a run's kernel returns, before its first stamp: (a recorded row not finite, rows
# written, NIS sum, updates, measurements rejected by the gate).
NO_TALLY = (False, 0, 0.0, 0, 0)


@maybe_njit
def stamp_input(u_odo, dt, k):
    """Stamp k of a timeline (timeline.Timeline): its odometry, the speed and the steering angle
    (bicycle) or turn rate (unicycle), and its step dt."""
    return u_odo[k, 0], u_odo[k, 1], dt[k]


@maybe_njit
def record(j, x, P, R, Qu, out_x, out_P, out_R, out_Q):
    """Row j of the records (out_x, out_P, out_R, out_Q); returns (j + 1, whether x or P has a
    value that is not finite)."""
    bad = False
    for i in range(3):
        out_x[j, i] = x[i]
        if not math.isfinite(x[i]):
            bad = True
    for i in range(9):
        out_P[j, i // 3, i % 3] = P[i]
        if not math.isfinite(P[i]):
            bad = True
    out_R[j, 0] = R[0]
    out_R[j, 1] = R[3]
    out_Q[j, 0] = Qu[0]
    out_Q[j, 1] = Qu[3]
    return j + 1, bad


@maybe_njit
def hph_diag(H, P):
    """diag(H P H^T) for the H of `innovation` (third column (0, -1))."""
    return hqh_diag(H, P, math.inf, math.inf)


# ---------------------------------------------------------------------------------------------
# The variational-Bayes filters (filters.vb), their rules as written there: the VB iteration's
# state update is `correct` above (the Joseph update of the filter itself), so only the noise
# posterior's rules come from filters/vb.py and the bounds from filters/adaptive.py.

vb_r_predict, vb_r_beta, vb_r_bounded_beta = jitable(
    _vb.vb_r_predict, _vb.vb_r_beta, _vb.vb_r_bounded_beta
)


# ---------------------------------------------------------------------------------------------
# Akhlaghi et al. (filters.akhlaghi): residual-based R, innovation-based Qu, their rules as
# written there; the Qu least squares and the interval's accumulators from filters/adaptive.py.

forget, residual_variance, state_noise_estimate = jitable(
    _akhlaghi.forget, _akhlaghi.residual_variance, _akhlaghi.state_noise_estimate
)


# ---------------------------------------------------------------------------------------------
# Huang et al.'s VBAKF (filters.vb.VBAKF): inverse-Wishart on P- and R, its rules as written in
# filters/vb.py.

vbakf_predict, vbakf_prior, inflation_cap, clip_covariance_2 = jitable(
    _vb.vbakf_predict, _vb.vbakf_prior, _vb.inflation_cap, _vb.clip_covariance_2
)


# ---------------------------------------------------------------------------------------------
# Fading-memory Sage-Husa (filters.sage_husa)


# ---------------------------------------------------------------------------------------------
# Innovation-based adaptive estimation (filters.iae)

window_covariance, window_mean, r_estimate, hold_nonpositive, q_estimate = jitable(
    _iae.window_covariance, _iae.window_mean, _iae.r_estimate, _iae.hold_nonpositive,
    _iae.q_estimate,
)  # fmt: skip
