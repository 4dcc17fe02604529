"""The wand bundle adjustment: one sparse least-squares solve over every camera and wand pose.

A global bundle adjustment (scipy least_squares, trf, analytic sparse Jacobian,
robust loss) refines all camera poses (optionally fx, fy, cx, cy), each camera's
clock offset, the wand's AB/AC ratio and one wand pose per frame. The wand is
parametrised as its A position plus a direction, so B = A + AB u and C = A + AC u
hold exactly: the wand lengths fix the scale and the wand's straightness is enforced.
The start comes from calibration/pairwise.py; calibration/wand_solve.py runs
the whole step (rounds, outlier views, observability guards).

Pose convention: x_cam = R x_world + t; the world is the reference camera's frame
until the ground-plane step moves it.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from visionpos.calibration.wand import WandSpec
from visionpos.camera.model import Camera
from visionpos.geometry.rotations import left_jacobian_SO3, skew
from visionpos.geometry.triangulation import CameraRig

ProgressFn = Callable[[str, int, int], None]  # progress(stage, done, total)


def no_progress(stage: str, done: int, total: int) -> None:
    """The default progress callback: reports nothing."""
    return None


# ------------------------------------------------------------ bundle adjustment
def _complement(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (F,3) orthogonal to u (F,3) and to each other."""
    helper = np.where(np.abs(u[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u, e1)
    return e1, e2


class _Problem:
    """Residuals and the analytic sparse Jacobian of the wand bundle adjustment."""

    def __init__(
        self,
        pixels: np.ndarray,
        cameras: list[Camera],
        R0: np.ndarray,
        t0: np.ndarray,
        A0: np.ndarray,
        u0: np.ndarray,
        spec: WandSpec,
        ref: int,
        refine_intrinsics: bool,
        velocity: np.ndarray | None = None,
        estimate_ratio: bool = False,
    ):
        F, V = pixels.shape[:2]
        self.F, self.V, self.ref = F, V, ref
        ok = np.isfinite(pixels).all(axis=3)  # (F, V, 3)
        f_o, v_o, k_o = np.nonzero(ok)
        self.f_o, self.v_o, self.k_o = f_o, v_o, k_o
        self.uv = pixels[f_o, v_o, k_o]
        self.M = len(f_o)
        self.spec = spec
        self.estimate_ratio = estimate_ratio
        # wand points move during a clock offset: X(t - eps) = X(t) - eps * velocity
        self.vel = None if velocity is None else velocity[f_o, k_o]  # (M, 3) m/s
        self.R0 = R0.copy()
        self.u0 = u0.copy()
        self.e1, self.e2 = _complement(u0)
        # distortion with unit focal length and zero centre: xd and d xd / d xn
        self.unit_rig = CameraRig(
            [
                replace(c, model=replace(c.model, fx=1.0, fy=1.0, cx=0.0, cy=0.0), R=np.eye(3), t=np.zeros(3))
                for c in cameras
            ]
        )
        self.f_cam = np.array([[c.model.fx, c.model.fy] for c in cameras])
        self.c_cam = np.array([[c.model.cx, c.model.cy] for c in cameras])
        self.refine_intrinsics = refine_intrinsics
        # parameter layout: [cams except ref: rotvec(3) t(3)] [intrinsics: fx fy cx cy] [clock offsets
        # except ref (s)] [wand ratio AB/AC] [frames: A(3) a b]
        self.cam_index = np.full(V, -1)
        others = [v for v in range(V) if v != ref]
        self.cam_index[others] = np.arange(len(others))
        self.n_cam = 6 * len(others)
        self.n_intr = 4 * V if refine_intrinsics else 0
        self.off_offsets = self.n_cam + self.n_intr
        self.n_off = len(others) if velocity is not None else 0
        self.off_ratio = self.off_offsets + self.n_off
        self.off_frames = self.off_ratio + (1 if estimate_ratio else 0)
        self.n = self.off_frames + 5 * F
        self.x0 = np.zeros(self.n)
        ci = self.cam_index >= 0
        self.x0[: self.n_cam] = np.column_stack([np.zeros((len(others), 3)), t0[ci]]).ravel()
        if refine_intrinsics:
            self.x0[self.n_cam : self.off_offsets] = np.column_stack([self.f_cam, self.c_cam]).ravel()
        if estimate_ratio:
            self.x0[self.off_ratio] = spec.ratio
        self.t_ref = t0[ref].copy()
        fr = np.zeros((F, 5))
        fr[:, :3] = A0
        self.x0[self.off_frames :] = fr.ravel()
        self._build_pattern()
        self._cache_x: np.ndarray | None = None

    def _build_pattern(self) -> None:
        M = self.M
        rows2 = np.arange(2 * M).reshape(M, 2)
        # frame block: 5 columns for every observation
        fcols = self.off_frames + 5 * self.f_o[:, None] + np.arange(5)
        blocks_r = [np.repeat(rows2[:, :, None], 5, axis=2)]
        blocks_c = [np.broadcast_to(fcols[:, None, :], (M, 2, 5))]
        self.has_cam = self.cam_index[self.v_o] >= 0
        idx = np.flatnonzero(self.has_cam)
        ccols = 6 * self.cam_index[self.v_o[idx]][:, None] + np.arange(6)
        blocks_r.append(np.repeat(rows2[idx][:, :, None], 6, axis=2))
        blocks_c.append(np.broadcast_to(ccols[:, None, :], (len(idx), 2, 6)))
        if self.refine_intrinsics:
            icols = self.n_cam + 4 * self.v_o[:, None] + np.arange(4)
            blocks_r.append(np.repeat(rows2[:, :, None], 4, axis=2))
            blocks_c.append(np.broadcast_to(icols[:, None, :], (M, 2, 4)))
        if self.n_off:
            ocols = self.off_offsets + self.cam_index[self.v_o[idx]]
            blocks_r.append(rows2[idx])
            blocks_c.append(np.broadcast_to(ocols[:, None], (len(idx), 2)))
        if self.estimate_ratio:
            blocks_r.append(rows2)
            blocks_c.append(np.full((M, 2), self.off_ratio))
        self.cam_obs = idx
        self.jrows = np.concatenate([b.ravel() for b in blocks_r])
        self.jcols = np.concatenate([np.asarray(b).ravel() for b in blocks_c])

    # -- unpacking
    def cameras_from(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """R (V,3,3), t (V,3), rotvec (V,3), f (V,2), c (V,2)."""
        V = self.V
        cam = x[: self.n_cam].reshape(-1, 6)
        rv = np.zeros((V, 3))
        t = np.zeros((V, 3))
        ci = self.cam_index >= 0
        rv[ci] = cam[:, :3]
        t[ci] = cam[:, 3:]
        t[self.ref] = self.t_ref
        R = Rotation.from_rotvec(rv).as_matrix() @ self.R0
        if self.refine_intrinsics:
            intr = x[self.n_cam : self.off_offsets].reshape(V, 4)
            f, c = intr[:, :2], intr[:, 2:]
        else:
            f, c = self.f_cam, self.c_cam
        return R, t, rv, f, c

    def offsets_from(self, x: np.ndarray) -> np.ndarray:
        """(V,) clock offset (s) of each camera left after the grid's correction (ref: 0)."""
        eps = np.zeros(self.V)
        if self.n_off:
            ci = self.cam_index >= 0
            eps[ci] = x[self.off_offsets : self.off_ratio]
        return eps

    def lengths_from(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """(wand offsets (3,), d offsets / d ratio (3,), ratio AB/AC)."""
        r = float(x[self.off_ratio]) if self.estimate_ratio else self.spec.ratio
        offs, doffs = self.spec.offsets_for_ratio(r)
        return offs, doffs, r

    def wand_from(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A (F,3), u (F,3), n (F,3) un-normalised direction."""
        fr = x[self.off_frames :].reshape(self.F, 5)
        n = self.u0 + fr[:, 3:4] * self.e1 + fr[:, 4:5] * self.e2
        u = n / np.linalg.norm(n, axis=1, keepdims=True)
        return fr[:, :3], u, n

    def _evaluate(self, x: np.ndarray) -> None:
        if self._cache_x is not None and np.array_equal(x, self._cache_x):
            return
        R, t, rv, f, c = self.cameras_from(x)
        A, u, n = self.wand_from(x)
        fo, vo = self.f_o, self.v_o
        offs, dL, _ = self.lengths_from(x)
        self.L, self.dL = offs[self.k_o], dL[self.k_o]
        X = A[fo] + self.L[:, None] * u[fo]
        if self.n_off:
            X = X - self.offsets_from(x)[vo][:, None] * self.vel
        Rv = R[vo]
        Z = np.einsum("mij,mj->mi", Rv, X)
        Xc = Z + t[vo]
        z = Xc[:, 2]
        z = np.where(np.abs(z) < 1e-9, 1e-9, z)
        xn = Xc[:, :2] / z[:, None]
        # distortion through the unit-focal rig, in the dense (F*3, V) layout it expects
        dense = np.zeros((self.F * 3, self.V, 2))
        slot = fo * 3 + self.k_o
        dense[slot, vo] = xn
        xd_d, Jd_d = self.unit_rig.distort(dense, with_jac=True)
        xd = xd_d[slot, vo]
        Jd = Jd_d[slot, vo]  # (M, 2, 2)
        fv = f[vo]
        self.res = xd * fv + c[vo] - self.uv
        self._fwd = (rv, u, n, Rv, Z, z, xn, xd, Jd, fv)
        self._cache_x = x.copy()
        self._jac_x: np.ndarray | None = None

    def _jacobian(self, x: np.ndarray) -> None:
        self._evaluate(x)
        if self._jac_x is not None:
            return
        rv, u, n, Rv, Z, z, xn, xd, Jd, fv = self._fwd
        fo, vo = self.f_o, self.v_o
        # d xn / d Xc
        Pz = np.zeros((self.M, 2, 3))
        Pz[:, 0, 0] = 1 / z
        Pz[:, 1, 1] = 1 / z
        Pz[:, 0, 2] = -xn[:, 0] / z
        Pz[:, 1, 2] = -xn[:, 1] / z
        G = np.einsum("mij,mjk->mik", fv[:, :, None] * Jd, Pz)  # (M,2,3) d uv / d Xc
        GR = np.einsum("mij,mjk->mik", G, Rv)  # d uv / d X world
        # direction: d u / d(a, b) = (I - u u^T) / |n| [e1 e2]
        nn = np.linalg.norm(n, axis=1)
        P_perp = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / nn[:, None, None]
        Du = np.einsum("fij,fjk->fik", P_perp, np.stack([self.e1, self.e2], axis=2))  # (F,3,2)
        Jab = np.einsum("mij,mjk->mik", GR, Du[fo]) * self.L[:, None, None]
        parts = [np.concatenate([GR, Jab], axis=2)]  # (M,2,5)
        ci = self.cam_obs
        if len(ci):
            Jl = left_jacobian_SO3(rv)  # (V,3,3)
            dZ = -np.einsum("mij,mjk->mik", skew(Z[ci]), Jl[vo[ci]])  # d Xc / d rotvec
            Jr = np.einsum("mij,mjk->mik", G[ci], dZ)
            parts.append(np.concatenate([Jr, G[ci]], axis=2))  # (Mc,2,6)
        if self.refine_intrinsics:
            Ji = np.zeros((self.M, 2, 4))
            Ji[:, 0, 0] = xd[:, 0]
            Ji[:, 1, 1] = xd[:, 1]
            Ji[:, 0, 2] = 1.0
            Ji[:, 1, 3] = 1.0
            parts.append(Ji)
        if self.n_off:
            parts.append(-np.einsum("mij,mj->mi", GR[ci], self.vel[ci]))  # (Mc, 2)
        if self.estimate_ratio:
            parts.append(np.einsum("mij,mj->mi", GR, u[fo]) * self.dL[:, None])  # (M, 2)
        self.jdata = np.concatenate([p.ravel() for p in parts])
        self._jframe = parts[0]
        self._jac_x = x

    def covariance(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        """(covariance of the non-frame parameters (n_small, n_small), residual variance px^2) at x.

        sigma^2 (J^T J)^-1 restricted to cameras, intrinsics, offsets and ratio: the wand-pose
        blocks (5x5 per frame, block-diagonal) are eliminated by the Schur complement, so
        nothing larger than n_small x n_small is inverted. An undetermined direction comes
        out with a huge variance instead of being hidden.
        """
        self._jacobian(x)
        J = self.jac(x).tocsc()
        ns = self.off_frames
        Jc, Jf = J[:, :ns], J[:, ns:]
        U = (Jc.T @ Jc).toarray()
        W = (Jc.T @ Jf).toarray().reshape(ns, self.F, 5)
        Vb = np.zeros((self.F, 5, 5))
        np.add.at(Vb, self.f_o, np.einsum("mai,maj->mij", self._jframe, self._jframe))
        Vb += 1e-12 * np.eye(5) * np.trace(Vb, axis1=1, axis2=2)[:, None, None]
        Vinv = np.linalg.inv(Vb)
        S = U - np.einsum("afi,fij,bfj->ab", W, Vinv, W)
        d = 1.0 / np.sqrt(np.maximum(np.diag(S), 1e-300))
        Sn = S * d[:, None] * d[None, :]
        cov_n = np.linalg.inv(Sn + 1e-13 * np.eye(ns))
        dof = max(2 * self.M - self.n, 1)
        sigma2 = float(np.sum(self.res**2) / dof)
        return cov_n * d[:, None] * d[None, :] * sigma2, sigma2

    def parameter_std(self, x: np.ndarray) -> dict:
        """Standard deviations at x: per camera rot_deg (V,), center_m (V,) (RMS over the axes
        of the camera centre), f_px (V, 2), c_px (V, 2) (refined intrinsics only), offset_s (V,)
        (estimated offsets only); ratio (AB/AC, when estimated); sigma_px."""
        cov, sigma2 = self.covariance(x)
        V = self.V
        R, t, rv, _, _ = self.cameras_from(x)
        out: dict = {"sigma_px": float(np.sqrt(sigma2)), "rot_deg": np.zeros(V), "center_m": np.zeros(V)}
        Jl = left_jacobian_SO3(rv)
        for v in range(V):
            k = self.cam_index[v]
            if k < 0:
                continue
            C6 = cov[6 * k : 6 * k + 6, 6 * k : 6 * k + 6]
            out["rot_deg"][v] = float(np.degrees(np.sqrt(max(np.trace(Jl[v] @ C6[:3, :3] @ Jl[v].T), 0) / 3)))
            # centre = -R^T t; a left rotation increment d moves it by R^T [t]x d
            Jc = np.hstack([-R[v].T @ skew(t[v][None])[0] @ Jl[v], -R[v].T])
            out["center_m"][v] = float(np.sqrt(max(np.trace(Jc @ C6 @ Jc.T), 0) / 3))
        sd = np.sqrt(np.maximum(np.diag(cov), 0))
        if self.refine_intrinsics:
            intr = sd[self.n_cam : self.off_offsets].reshape(V, 4)
            out["f_px"], out["c_px"] = intr[:, :2], intr[:, 2:]
            out["intrinsics_correlation"] = self.intrinsics_correlation(cov)
        if self.n_off:
            off = np.zeros(V)
            off[self.cam_index >= 0] = sd[self.off_offsets : self.off_ratio]
            out["offset_s"] = off
        if self.estimate_ratio:
            out["ratio"] = float(sd[self.off_ratio])
        return out

    def parameter_names(self) -> list[str]:
        """Names of the non-frame parameters in their order (camera v as `cam{v}`: the caller names them)."""
        names = []
        for v in np.flatnonzero(self.cam_index >= 0):
            names += [f"cam{v} rotation {a}" for a in "xyz"] + [f"cam{v} position t{a}" for a in "xyz"]
        if self.refine_intrinsics:
            names += [f"cam{v} {p}" for v in range(self.V) for p in ("fx", "fy", "cx", "cy")]
        names += [f"cam{v} clock offset" for v in np.flatnonzero(self.cam_index >= 0)][: self.n_off]
        if self.estimate_ratio:
            names.append("wand ratio")
        return names

    def intrinsics_correlation(self, cov: np.ndarray) -> dict:
        """How far the data separate each camera's fx, fy, cx, cy from every other parameter, from the
        covariance (n_small, n_small): `multiple` (V, 4) the multiple correlation with all the others
        (sqrt(1 - 1/(C_ii (C^-1)_ii)): 1 when the others explain it entirely, as a focal length and the
        distances two cameras see the wand at), `partner` (V, 4) the index of the most correlated single
        parameter (`parameter_names`) and `partner_corr` (V, 4) that correlation."""
        d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
        corr = cov / d[:, None] / d[None, :]
        info = np.linalg.pinv(corr)
        V = self.V
        multiple, partner, pcorr = np.zeros((V, 4)), np.zeros((V, 4), int), np.zeros((V, 4))
        for v in range(V):
            for k in range(4):
                i = self.n_cam + 4 * v + k
                vif = max(float(corr[i, i] * info[i, i]), 1.0)
                multiple[v, k] = np.sqrt(1.0 - 1.0 / vif)
                row = np.abs(corr[i]).copy()
                row[i] = -1.0
                row[self.n_cam + 4 * v: self.n_cam + 4 * v + 4] = -1.0  # its own camera's others: not the question
                partner[v, k] = int(np.argmax(row))
                pcorr[v, k] = float(corr[i, partner[v, k]])
        return {"multiple": multiple, "partner": partner, "partner_corr": pcorr, "names": self.parameter_names()}

    def fun(self, x: np.ndarray) -> np.ndarray:
        self._evaluate(x)
        return self.res.ravel()

    def jac(self, x: np.ndarray) -> sp.csr_matrix:
        self._jacobian(x)
        return sp.csr_matrix((self.jdata, (self.jrows, self.jcols)), shape=(2 * self.M, self.n))


def bundle_adjust(
    pixels: np.ndarray,
    cameras: list[Camera],
    R: np.ndarray,
    t: np.ndarray,
    A: np.ndarray,
    u: np.ndarray,
    spec: WandSpec,
    ref: int = 0,
    refine_intrinsics: bool = False,
    loss: str = "soft_l1",
    f_scale: float = 1.0,
    max_nfev: int = 50,
    progress: ProgressFn = no_progress,
    velocity: np.ndarray | None = None,
    estimate_ratio: bool = False,
    covariance: bool = False,
) -> tuple[list[Camera], np.ndarray, np.ndarray, np.ndarray, dict]:
    """One least-squares solve over all cameras and wand poses.

    pixels: (F, V, 3, 2) observations (NaN = missing); R (V,3,3), t (V,3) initial
    poses; A (F,3), u (F,3) initial wand. Camera `ref` keeps its pose (gauge);
    the wand lengths fix the scale.
    velocity: (F, 3, 3) m/s of A, B, C: also estimate each camera's clock offset left
    in the observations' times (camera `ref` keeps 0). estimate_ratio: also estimate the
    wand's AB/AC with the spec's `known` segment fixed. covariance: add info['std']
    (Problem.parameter_std).
    Returns refined cameras, A, u, residuals (F, V, 3, 2) px (NaN where unobserved)
    and solver info (with offsets_s (V,) and ratio).
    """
    prob = _Problem(pixels, cameras, R, t, A, u, spec, ref, refine_intrinsics, velocity, estimate_ratio)
    calls = [0]

    def fun(x: np.ndarray) -> np.ndarray:
        calls[0] += 1
        progress("bundle adjustment", min(calls[0], max_nfev), max_nfev)
        return prob.fun(x)

    sol = least_squares(
        fun,
        prob.x0,
        jac=prob.jac,
        method="trf",
        loss=loss,
        f_scale=f_scale,
        x_scale="jac",
        tr_solver="lsmr",
        max_nfev=max_nfev,
        xtol=1e-8,
        ftol=1e-6,
        gtol=1e-8,
    )
    progress("bundle adjustment", max_nfev, max_nfev)  # converged: close the bar
    Rn, tn, _, f, c = prob.cameras_from(sol.x)
    A2, u2, _ = prob.wand_from(sol.x)
    prob._evaluate(sol.x)
    res = np.full(pixels.shape, np.nan)
    res[prob.f_o, prob.v_o, prob.k_o] = prob.res
    out = []
    for v, cam in enumerate(cameras):
        model = cam.model
        if refine_intrinsics:
            model = replace(model, fx=float(f[v, 0]), fy=float(f[v, 1]), cx=float(c[v, 0]), cy=float(c[v, 1]))
        out.append(replace(cam, model=model, R=Rn[v], t=tn[v]))
    info = {"nfev": int(sol.nfev), "cost": float(sol.cost), "message": str(sol.message), "n_params": prob.n,
            "n_residuals": 2 * prob.M, "offsets_s": prob.offsets_from(sol.x), "ratio": prob.lengths_from(sol.x)[2]}
    if covariance:
        info["std"] = prob.parameter_std(sol.x)
    return out, A2, u2, res, info
