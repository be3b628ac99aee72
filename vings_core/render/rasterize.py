"""Public API of the 2DGS rasterizer: :func:`rasterize_2dgs`, :func:`gaussian_scores`.

Pipeline (CPU): torch set-up per Gaussian (:mod:`.project`, SH colours; autograd) -> numba culling,
exact screen boxes, depth sort, 16x16 tile binning, tile-parallel compositing
(:mod:`.kernels`) -> torch outputs. Backward: numba back-to-front pass over (optionally sampled)
pixels gives dL/d(M, opacity, rgb, normal) per Gaussian; torch autograd carries them to means,
quats, scales, opacities, colours / SH and the camera pose.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Optional, Union

import numba
import numpy as np
import torch

from ..errors import InputError
from ..geometry import skew
from ..types import CameraModel
from . import kernels as K
from .project import pack_params, project_surfels
from .sh import sh_to_color

ArrayLike = Union[torch.Tensor, np.ndarray]


@dataclass
class RenderOutput:
    """Result of :func:`rasterize_2dgs` for one camera (``H x W``, ``N`` Gaussians).

    Per pixel (differentiable): ``color (H,W,3)`` (background composited), ``depth (H,W)``
    accumulated depth ``sum_i w_i z_i`` in m, where ``z_i`` is the camera z of the ray-splat hit
    point (centre depth when the low-pass filter dominates) and ``w_i = alpha_i T_i``; divide by
    ``alpha`` for the expected depth (:attr:`expected_depth`); ``normal (H,W,3)`` accumulated
    surfel normals in the *camera* frame, facing the camera (see :meth:`normal_world`);
    ``alpha (H,W)`` accumulated opacity ``1 - T``; ``distortion (H,W)`` the 2DGS depth-distortion
    term ``sum_{i,j<i} w_i w_j (m_i - m_j)^2`` with ``m`` 2DGS's mapped depth.

    Per Gaussian (not differentiable): ``radii`` half extent of the screen box in px (0 = culled),
    ``pixels_touched`` pixels it contributed to, ``contribution`` ``sum alpha T`` over them,
    ``error`` ``sum L(u) alpha T`` for the ``loss_map`` given to the forward (``None`` otherwise),
    ``means2d (N,2)`` projected centres in px. ``n_contrib (H,W)``: Gaussians composited per pixel.
    ``stats``: counts (``pairs_evaluated`` pixel-Gaussian alpha evaluations in the forward,
    ``tile_pairs``, ``visible``, and after a backward ``bwd_pairs_evaluated``, ``bwd_pixels`` and
    ``bwd_raster_ms``, the time of the rasterizer's own backward: pixel selection, tile kernel and
    per-Gaussian reduction).
    """

    color: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    alpha: torch.Tensor
    distortion: torch.Tensor
    radii: torch.Tensor
    pixels_touched: torch.Tensor
    contribution: torch.Tensor
    error: Optional[torch.Tensor]
    means2d: torch.Tensor
    n_contrib: torch.Tensor
    stats: dict = field(default_factory=dict)
    _state: object = None

    @property
    def expected_depth(self) -> torch.Tensor:
        """``depth / alpha`` (m), 0 where nothing was rendered."""
        return self.depth / self.alpha.clamp_min(1e-10)

    def normal_world(self, T_wc: ArrayLike) -> torch.Tensor:
        """Accumulated normals rotated to the world frame with camera-to-world ``T_wc``."""
        R = torch.as_tensor(np.asarray(T_wc) if not torch.is_tensor(T_wc) else T_wc)[:3, :3]
        return self.normal @ R.to(self.normal.dtype).T

    def set_sample_map(self, score: ArrayLike) -> None:
        """Per-pixel score ``(H, W)`` (e.g. this render's L1 error) that the sampled backward
        uses to pick, per 16x16 tile, the ``sample_ratio`` fraction of pixels to back-propagate.
        Call after the forward and before ``backward()``; overrides the forward's ``loss_map``."""
        st = self._state
        if st is None:
            raise InputError("set_sample_map: this render has no numba backward state")
        score = _as_numpy(score, np.float64, "sample map")
        if score.shape != (st.height, st.width):
            raise InputError(f"sample map: expected shape {(st.height, st.width)}, got {score.shape}")
        st.sample_map = score


class _State:
    """Arrays kept from the forward for the backward (numpy, working dtype)."""

    def __init__(self, width: int, height: int, near: float, far: float, sample_ratio: float,
                 sample_map: Optional[np.ndarray]):
        self.width, self.height, self.near, self.far = width, height, near, far
        self.sample_ratio = sample_ratio
        self.sample_map = sample_map
        self.stats: dict = {}


def _as_numpy(a: ArrayLike, dtype, what: str) -> np.ndarray:
    """A private C-contiguous copy (the caller may change its tensor before the backward)."""
    if torch.is_tensor(a):
        a = a.detach().cpu().numpy()
    try:
        return np.array(a, dtype=dtype, order="C", copy=True)
    except (TypeError, ValueError, RuntimeError, NotImplementedError) as e:
        raise InputError(f"{what}: cannot convert to a {np.dtype(dtype).name} array ({e})") from None


class _Scratch(threading.local):
    """Per-thread scratch arrays for the backward's per-pair rows, kept between calls.

    At 300k Gaussians the pair rows are ~27 MB: a fresh allocation each backward is a fresh
    mapping that the kernel zero-fills page by page (a few ms of CPU), a cost the sampled backward
    pays in full however few pairs it visits. Every row is written before it is read (rows a
    pass does not visit are flagged unused), so reuse needs no clearing. Per thread, so
    concurrent renders never share one; the per-Gaussian sums go to a fresh array. A thread keeps
    the largest buffers it needed (~90 bytes per tile-list entry) until it ends.
    """

    MAX_BYTES = 1 << 30   # a larger request is allocated afresh and not kept

    def __init__(self):
        self.bufs: dict = {}

    def get(self, name: str, shape: tuple, dtype) -> np.ndarray:
        dtype = np.dtype(dtype)
        need = int(np.prod(shape)) * dtype.itemsize
        if need > self.MAX_BYTES:
            return np.empty(shape, dtype)
        buf = self.bufs.get(name)
        if buf is None or buf.nbytes < need:
            buf = np.empty(max(need, int(1.25 * (0 if buf is None else buf.nbytes))), np.uint8)
            self.bufs[name] = buf
        return buf[:need].view(dtype).reshape(shape)


_SCRATCH = _Scratch()


def _nchunk() -> int:
    return max(1, 4 * numba.get_num_threads())


class _Threads:
    """Run small problems on the calling thread only: waking the numba worker pool costs more than
    it saves below a few thousand Gaussians (and much more on a loaded machine)."""

    SMALL_PIXELS = 128 * 128
    SMALL_GAUSSIANS = 20000

    def __init__(self, width: int, height: int, n: int):
        self.serial = width * height <= self.SMALL_PIXELS and n <= self.SMALL_GAUSSIANS

    def __enter__(self):
        if self.serial:
            self._old = numba.get_num_threads()
            numba.set_num_threads(1)
        return self

    def __exit__(self, *exc):
        if self.serial:
            numba.set_num_threads(self._old)
        return False


def _forward_numpy(st: _State, params: np.ndarray, bg: np.ndarray, loss: Optional[np.ndarray]):
    dt = params.dtype
    W, H = st.width, st.height
    N = params.shape[0]
    cst = K.make_consts(dt, st.near, st.far)
    aux = np.empty((N, K.AUX), dt)
    bbox = np.empty((N, 4), np.int32)
    radii = np.empty(N, np.int32)
    ntiles = np.empty(N, np.int32)
    if N:
        K.preprocess(params, cst, W, H, aux, bbox, radii, ntiles)
    vis = np.flatnonzero(ntiles > 0)
    z = np.ascontiguousarray(params[vis, 8])
    if dt == np.float32:
        order = vis[K.radix_argsort_u32(z.view(np.uint32))]
    else:
        order = vis[np.argsort(z, kind="stable")]
    order = np.ascontiguousarray(order, dtype=np.int64)
    tile_off, gids, xstart, gslot, pbox = K.bin_tiles(order, bbox, aux, ntiles, W, H, _nchunk())
    npair = gids.shape[0]
    nrows = N + int(xstart[N])  # per-pair rows: one per Gaussian + extra tiles (bin_tiles)
    xs = np.arange(W, dtype=dt)
    ys = np.arange(H, dtype=dt)
    out_rgb = np.empty((H, W, 3), dt)
    out_depth = np.empty((H, W), dt)
    out_normal = np.empty((H, W, 3), dt)
    out_alpha = np.empty((H, W), dt)
    out_dist = np.empty((H, W), dt)
    out_T = np.empty((H, W), dt)
    out_last = np.empty((H, W), np.int32)
    out_count = np.empty((H, W), np.int32)
    out_d1 = np.empty((H, W), dt)
    out_d2 = np.empty((H, W), dt)
    pair_stats = _SCRATCH.get("pair_stats", (nrows, K.NSTAT), dt)   # reduced below
    pmask = np.empty((npair, 4), np.uint64)
    ntile = tile_off.shape[0] - 1
    tile_evals = np.zeros(ntile, np.int64)
    has_loss = loss is not None
    loss_arr = loss.astype(dt, copy=False) if has_loss else np.zeros((1, 1), dt)
    with K.tile_parallel():
        K.forward_tiles(params, aux, pbox, tile_off, gids, gslot, cst, W, H, xs, ys, bg, loss_arr,
                        has_loss, out_rgb, out_depth, out_normal, out_alpha, out_dist, out_T,
                        out_last, out_count, out_d1, out_d2, pair_stats, pmask, tile_evals)
    scores = np.empty((N, K.NSTAT), dt)
    K.reduce_pairs(pair_stats, np.empty(0, np.uint8), xstart, ntiles, scores)
    st.params, st.aux, st.bg = params, aux, bg
    st.tile_off, st.gids, st.xstart, st.gslot = tile_off, gids, xstart, gslot
    st.pmask, st.ntiles, st.nrows = pmask, ntiles, nrows
    st.T_final, st.last, st.d1, st.d2 = out_T, out_last, out_d1, out_d2
    st.stats = {"pairs_evaluated": int(tile_evals.sum()), "tile_pairs": int(npair),
                "visible": int(vis.size), "pairs_contributing": int(out_count.sum(dtype=np.int64))}
    means2d = aux[:, :2].copy()
    return (out_rgb, out_depth, out_normal, out_alpha, out_dist, out_count, radii, scores,
            has_loss, means2d)


def _backward_numpy(st: _State, g_rgb, g_depth, g_normal, g_alpha, g_dist,
                    want_bg: bool = True) -> tuple:
    """Per-Gaussian dL/d record ``(N, 16)`` and dL/d background (``None`` unless ``want_bg``)."""
    t0 = time.perf_counter()
    dt = st.params.dtype
    W, H = st.width, st.height
    N = st.params.shape[0]
    sel = np.ones((H, W), np.uint8)
    if st.sample_ratio < 1.0:
        if st.sample_map is not None:
            score = st.sample_map
        else:
            score = (np.abs(g_rgb).sum(-1) + np.abs(g_depth) + np.abs(g_normal).sum(-1)
                     + np.abs(g_alpha) + np.abs(g_dist)).astype(np.float64)
        K.select_pixels(np.ascontiguousarray(score, dtype=np.float64), float(st.sample_ratio), sel)
    pair_grad = _SCRATCH.get("pair_grad", (st.nrows, K.NGRAD), dt)
    pair_used = _SCRATCH.get("pair_used", (st.nrows,), np.uint8)
    tile_evals = np.zeros(st.tile_off.shape[0] - 1, np.int64)
    with K.tile_parallel():
        K.backward_tiles(st.params, st.aux, st.pmask, st.tile_off, st.gids, st.gslot,
                         K.make_consts(dt, st.near, st.far), W, H, np.arange(W, dtype=dt),
                         np.arange(H, dtype=dt), st.bg, st.T_final, st.last, st.d1, st.d2,
                         g_rgb, g_depth, g_normal, g_alpha, g_dist, sel, pair_grad, pair_used,
                         tile_evals)
    # summed straight into a fresh array: the scratch rows are reused by the next backward
    grads = np.empty((N, K.NGRAD), dt)
    K.reduce_pairs(pair_grad, pair_used, st.xstart, st.ntiles, grads)
    g_bg = np.einsum("hw,hwc->c", st.T_final * sel, g_rgb) if want_bg else None
    st.stats["bwd_raster_ms"] = (time.perf_counter() - t0) * 1e3
    st.stats["bwd_pairs_evaluated"] = int(tile_evals.sum())
    st.stats["bwd_pixels"] = int(sel.sum(dtype=np.int64))
    return grads, g_bg


class _Rasterize2DGS(torch.autograd.Function):
    @staticmethod
    def forward(ctx, params, background, st, loss, out_holder):
        p = params.detach().cpu().numpy()
        p = np.ascontiguousarray(p)
        bg = np.array(background.detach().cpu().numpy(), order="C", copy=True)
        with _Threads(st.width, st.height, p.shape[0]):
            res = _forward_numpy(st, p, bg, loss)
        ctx.st = st
        out_holder.extend(res[5:])
        t = [torch.from_numpy(a) for a in res[:5]]
        return tuple(t)

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_normal, g_alpha, g_dist):
        st = ctx.st
        dt = st.params.dtype

        def np_(g):
            return np.ascontiguousarray(g.detach().cpu().numpy().astype(dt, copy=False))

        want_bg = bool(ctx.needs_input_grad[1])  # a constant background needs no gradient
        with _Threads(st.width, st.height, st.params.shape[0]):
            grads, g_bg = _backward_numpy(st, np_(g_rgb), np_(g_depth), np_(g_normal),
                                          np_(g_alpha), np_(g_dist), want_bg)
        return (torch.from_numpy(grads), torch.from_numpy(g_bg) if want_bg else None, None, None,
                None)


def _check(name: str, t, shape_tail: tuple, n: Optional[int]) -> torch.Tensor:
    if not torch.is_tensor(t):
        t = torch.as_tensor(np.asarray(t))
    if t.dim() != len(shape_tail) + 1 or tuple(t.shape[1:]) != shape_tail or (
            n is not None and t.shape[0] != n):
        want = ("N" if n is None else str(n),) + tuple(str(s) for s in shape_tail)
        raise InputError(f"rasterize_2dgs: {name} must have shape ({', '.join(want)}), "
                         f"got {tuple(t.shape)}")
    return t


def _finite_tensor(name: str, value, shape: tuple) -> torch.Tensor:
    """``value`` as a tensor (a tensor is kept as given: it may carry gradients; anything else
    becomes float64) of ``shape`` with finite entries, else InputError naming ``name``."""
    try:
        t = value if torch.is_tensor(value) else torch.as_tensor(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError) as e:
        raise InputError(f"rasterize_2dgs: {name} must be a {shape} array ({e})") from None
    if tuple(t.shape) != shape:
        raise InputError(f"rasterize_2dgs: {name} must have shape {shape}, got {tuple(t.shape)}")
    if t.device.type == "meta" or not bool(torch.isfinite(t.detach()).all()):
        raise InputError(f"rasterize_2dgs: {name} has non-finite entries")
    return t


#: largest image side the renderer accepts (its per-pixel buffers are allocated per call)
MAX_IMAGE_SIDE = 16384


def _number(name: str, value) -> float:
    """``value`` as a float; InputError naming the argument otherwise."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(f"rasterize_2dgs: {name} must be a number, got {value!r}") from None


def _check_opacities(o: torch.Tensor) -> None:
    """Finite opacities must be activated, in [0, 1] (non-finite ones are culled: module doc).
    One min/max pass when all is well (numpy on the CPU: torch's spins up its thread pool)."""
    if not o.numel():
        return
    lo, hi = (torch.aminmax(o) if o.is_cuda else (o.numpy().min(), o.numpy().max()))
    if float(lo) >= 0 and float(hi) <= 1:
        return
    bad = ((o < 0) | (o > 1)) & torch.isfinite(o)
    if bool(bad.any()):
        raise InputError(f"rasterize_2dgs: opacities must be activated, in [0, 1]; got "
                         f"{float(o[bad][0]):.6g} (Gaussian {int(bad.nonzero()[0, 0])})")


def _loss_map(loss_map: Optional[ArrayLike], H: int, W: int) -> Optional[torch.Tensor]:
    """``loss_map`` as an ``(H, W)`` tensor of finite values (None stays None); InputError otherwise.
    Checked once for both routes."""
    if loss_map is None:
        return None
    t = loss_map.detach() if torch.is_tensor(loss_map) else torch.from_numpy(
        _as_numpy(loss_map, np.float64, "loss_map"))
    if tuple(t.shape) != (H, W):
        raise InputError(f"rasterize_2dgs: loss_map must have shape {(H, W)}, got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise InputError(f"rasterize_2dgs: loss_map has {int((~torch.isfinite(t)).sum())} non-finite "
                         "pixels (they would make the error score NaN)")
    return t


def _prepare(means, quats, scales, opacities, colors, T_cw, camera, sh_degree, pose_delta,
             near, far):
    """Validate inputs; return (means, quats, scales, opacities, colors, T_cw tensor, pose_delta).

    Shapes, dtypes, devices and the pose are checked here; non-finite Gaussian parameters are not
    (a per-render scan would cost more than the kernels' culling of such Gaussians)."""
    if not isinstance(camera, CameraModel):
        raise InputError(f"rasterize_2dgs: camera must be a CameraModel, got {type(camera).__name__}")
    if camera.is_distorted:
        raise InputError("rasterize_2dgs: camera has lens distortion; render with the undistorted "
                         "model (CameraModel.undistorted()) and undistort the images")
    if max(camera.width, camera.height) > MAX_IMAGE_SIDE:
        raise InputError(f"rasterize_2dgs: camera {camera.width}x{camera.height} is larger than "
                         f"{MAX_IMAGE_SIDE} px per side")
    means = _check("means", means, (3,), None)
    N = means.shape[0]
    if means.dtype not in (torch.float32, torch.float64):
        raise InputError(f"rasterize_2dgs: means must be float32 or float64, got {means.dtype}")
    if means.device.type not in ("cpu", "cuda"):
        raise InputError(f"rasterize_2dgs: means are on device {means.device.type!r}; need cpu or cuda")
    quats = _check("quats (xyzw)", quats, (4,), N)
    scales = _check("scales", scales, (2,), N)
    opacities = torch.as_tensor(opacities) if not torch.is_tensor(opacities) else opacities
    if opacities.shape != (N,):
        raise InputError(f"rasterize_2dgs: opacities must have shape ({N},), got {tuple(opacities.shape)}")
    if sh_degree is None:
        colors = _check("colors", colors, (3,), N)
    else:
        if isinstance(sh_degree, bool) or not isinstance(sh_degree, (int, np.integer)):
            raise InputError(f"rasterize_2dgs: sh_degree must be an integer 0..3 or None, got {sh_degree!r}")
        if not torch.is_tensor(colors):
            colors = torch.as_tensor(np.asarray(colors))
        if colors.dim() != 3 or colors.shape[0] != N or colors.shape[2] != 3:
            raise InputError(f"rasterize_2dgs: with sh_degree, colors must be SH coefficients of shape "
                             f"({N}, K, 3), got {tuple(getattr(colors, 'shape', ()))}")
        if not 0 <= int(sh_degree) <= 3 or colors.shape[1] < (int(sh_degree) + 1) ** 2:
            raise InputError(f"rasterize_2dgs: sh_degree={sh_degree} needs 0..3 and at least "
                             f"{(int(sh_degree) + 1) ** 2} coefficients, got {colors.shape[1]}")
    for name, t in (("quats", quats), ("scales", scales), ("opacities", opacities), ("colors", colors)):
        if t.device != means.device:
            raise InputError(f"rasterize_2dgs: {name} are on {t.device}, means on {means.device}; "
                             f"put every input on one device")
    _check_opacities(opacities.detach())
    T = _finite_tensor("T_cw", T_cw, (4, 4))
    if pose_delta is not None:
        pose_delta = _finite_tensor("pose_delta", pose_delta, (6,))
    near, far = _number("near", near), _number("far", far)
    if not (0 < near < far):
        raise InputError(f"rasterize_2dgs: need 0 < near < far, got near={near}, far={far}")
    return means, quats, scales, opacities, colors, T, pose_delta


def apply_pose_delta(pose_delta: torch.Tensor, T_cw: torch.Tensor) -> torch.Tensor:
    """``se3_exp(pose_delta) @ T_cw`` in float64, differentiable at ``pose_delta = 0``.

    Uses the matrix exponential of the twist ``[[phi^, rho], [0, 0]]``, which equals
    :func:`vings_core.geometry.se3_exp` (``[rho, phi]`` order, left Jacobian).
    """
    d = pose_delta.to(torch.float64)
    X = torch.zeros(4, 4, dtype=torch.float64, device=d.device)
    X[:3, :3] = skew(d[3:])
    X[:3, 3] = d[:3]
    return torch.linalg.matrix_exp(X) @ T_cw.to(torch.float64)


class _ProjectSurfels(torch.autograd.Function):
    """Numba per-Gaussian set-up (:func:`.kernels.project_fwd`) with its hand-written chain rule
    (:func:`.kernels.project_bwd`); tested against the torch version :func:`.project.project_surfels`."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, rgb, T_cw, intr):
        dt = means.dtype
        np_ = [np.ascontiguousarray(t.detach().cpu().numpy()) for t in (means, quats, scales,
                                                                        opacities, rgb)]
        T = T_cw.detach().cpu().numpy().astype(np.float64)
        Rcw, tcw = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
        n = np_[0].shape[0]
        out = np.empty((n, K.NPARAM), np_[0].dtype)
        sign = np.empty(n, np_[0].dtype)
        if n:
            with _Threads(0, 0, n):
                K.project_fwd(*np_, Rcw, tcw, *intr, out, sign)
        # the tensors, not numpy views of them: autograd's version check then refuses a backward
        # after the caller changed them in place (a view would silently give wrong gradients)
        ctx.save_for_backward(means, quats, scales)
        ctx.save = (sign, Rcw, intr)
        return torch.from_numpy(out).to(dt)

    @staticmethod
    def backward(ctx, dpar):
        sign, Rcw, intr = ctx.save
        means, quats, scales = (np.ascontiguousarray(t.detach().cpu().numpy()) for t in ctx.saved_tensors)
        n = means.shape[0]
        want_pose = bool(ctx.needs_input_grad[5])
        dp = np.ascontiguousarray(dpar.detach().cpu().numpy().astype(means.dtype, copy=False))
        d_means = np.empty_like(means)
        d_quats = np.empty_like(quats)
        d_scales = np.empty_like(scales)
        d_opac = np.empty(n, dp.dtype)
        d_rgb = np.empty((n, 3), dp.dtype)
        d_pose = np.empty((n if want_pose else 1, 12), np.float64)
        if n:
            with _Threads(0, 0, n):
                K.project_bwd(means, quats, scales, sign, dp, Rcw, *intr, want_pose, d_means,
                              d_quats, d_scales, d_opac, d_rgb, d_pose)
        dT = None
        if want_pose:
            acc = d_pose[:n].sum(0) if n else np.zeros(12)
            dT = torch.zeros(4, 4, dtype=torch.float64)
            dT[:3, :3] = torch.from_numpy(acc[:9].reshape(3, 3))
            dT[:3, 3] = torch.from_numpy(acc[9:])
        return (torch.from_numpy(d_means), torch.from_numpy(d_quats), torch.from_numpy(d_scales),
                torch.from_numpy(d_opac).to(dpar.dtype), torch.from_numpy(d_rgb).to(dpar.dtype), dT, None)


def _camera_setup(means, quats, scales, opacities, colors, T, camera, sh_degree, pose_delta,
                  projector: str = "numba"):
    """Per-Gaussian record ``(N, 16)`` for the kernels, differentiable (numba or torch set-up)."""
    dt = means.dtype
    T = T.to(torch.float64)
    if pose_delta is not None:
        T = apply_pose_delta(pose_delta, T)
    if sh_degree is not None:
        Td = T.to(dt)
        R_cw, t_cw = Td[:3, :3], Td[:3, 3]
        rgb = sh_to_color(int(sh_degree), colors.to(dt), means - (-R_cw.T @ t_cw))
    else:
        rgb = colors.to(dt)
    if projector == "torch":
        proj = project_surfels(means, quats.to(dt), scales.to(dt), T.to(dt), camera.fx, camera.fy,
                               camera.cx, camera.cy)
        return pack_params(proj.M, opacities.to(dt), rgb, proj.normals)
    intr = (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    return _ProjectSurfels.apply(means, quats.to(dt), scales.to(dt), opacities.to(dt), rgb, T,
                                 intr)


def rasterize_2dgs(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                   opacities: torch.Tensor, colors: torch.Tensor, T_cw: ArrayLike,
                   camera: CameraModel, *, sh_degree: Optional[int] = None,
                   pose_delta: Optional[torch.Tensor] = None,
                   background: Optional[ArrayLike] = None, sample_ratio: float = 1.0,
                   loss_map: Optional[ArrayLike] = None, near: float = 0.01, far: float = 1e3,
                   backend: str = "auto") -> RenderOutput:
    """Render ``N`` 2D Gaussian surfels into one pinhole camera; differentiable by autograd.

    Args:
        means: ``(N, 3)`` centres, world frame, m (float32 or float64: the working precision).
        quats: ``(N, 4)`` rotations ``(x, y, z, w)`` (normalised here); columns 0/1 of the rotation
            are the splat's tangent axes, column 2 its normal.
        scales: ``(N, 2)`` standard deviations along the tangent axes, m (activated, > 0).
        opacities: ``(N,)`` in [0, 1] (activated).
        colors: ``(N, 3)`` RGB, or with ``sh_degree`` SH coefficients ``(N, K, 3)``
            (colour = max(SH(dir) + 0.5, 0) as in 3DGS/gsplat).
        T_cw: ``(4, 4)`` world-to-camera pose (tensor or array; a tensor may carry gradients).
        camera: undistorted :class:`CameraModel` (pixel centre of column j is x = j).
        pose_delta: optional ``(6,)`` se(3) tangent ``[rho, phi]``; the render uses
            ``se3_exp(pose_delta) @ T_cw`` so its gradient at 0 refines the pose (left update).
        background: ``(3,)`` colour behind the Gaussians (default black); differentiable.
        sample_ratio: fraction r in (0, 1] of pixels per 16x16 tile that the backward pass
            back-propagates (VINGS-Mono "sample rasterizer"); 1 = full backward. The pixels with the
            highest score are kept: the map set with :meth:`RenderOutput.set_sample_map`, else
            ``loss_map``, else the per-pixel sum of ``|dL/d output|``. Kept pixels are not rescaled.
        loss_map: optional ``(H, W)`` per-pixel loss ``L(u)``: the forward then fills the
            Gaussians' error score ``sum L(u) alpha T``; also the default sampling score.
        near, far: clipping distances (m) for Gaussian centres; hit points must lie beyond near.
        backend: ``"auto"`` (gsplat for CUDA tensors when importable, else numba), ``"numba"``,
            ``"gsplat"``.
    """
    if backend not in ("auto", "numba", "gsplat"):
        raise InputError(f"rasterize_2dgs: unknown backend {backend!r} (auto, numba, gsplat)")
    if not (0.0 < _number("sample_ratio", sample_ratio) <= 1.0):
        raise InputError(f"rasterize_2dgs: sample_ratio must be in (0, 1], got {sample_ratio}")
    means, quats, scales, opacities, colors, T, pose_delta = _prepare(
        means, quats, scales, opacities, colors, T_cw, camera, sh_degree, pose_delta, near, far)
    loss_map = _loss_map(loss_map, camera.height, camera.width)
    if backend == "gsplat" or (backend == "auto" and means.is_cuda):
        from .gsplat_backend import gsplat_available, rasterize_gsplat
        if gsplat_available():
            return rasterize_gsplat(means, quats, scales, opacities, colors, T, camera,
                                    sh_degree=sh_degree, pose_delta=pose_delta,
                                    background=background, near=near, far=far, loss_map=loss_map)
        if backend == "gsplat":
            raise InputError("rasterize_2dgs: backend='gsplat' needs CUDA and the gsplat package")
    if means.is_cuda:
        raise InputError("rasterize_2dgs: CUDA tensors need gsplat; move the Gaussians to the CPU")
    dt = means.dtype
    H, W = camera.height, camera.width
    params = _camera_setup(means, quats, scales, opacities, colors, T, camera, sh_degree,
                           pose_delta)
    try:
        bg = torch.zeros(3, dtype=dt) if background is None else torch.as_tensor(background).to(dt)
    except (TypeError, ValueError, RuntimeError) as e:
        raise InputError(f"rasterize_2dgs: background must be a (3,) colour ({e})") from None
    if bg.shape != (3,):
        raise InputError(f"rasterize_2dgs: background must have shape (3,), got {tuple(bg.shape)}")
    if not bool(torch.isfinite(bg.detach()).all()):
        raise InputError(f"rasterize_2dgs: background has non-finite values {bg.detach().tolist()}")
    loss = None if loss_map is None else _as_numpy(loss_map, np.float64, "loss_map")
    st = _State(W, H, float(near), float(far), float(sample_ratio), loss)
    holder: list = []
    color, depth, normal, alpha, dist = _Rasterize2DGS.apply(params, bg, st, loss, holder)
    count, radii, scores, has_loss, means2d = holder
    return RenderOutput(
        color=color, depth=depth, normal=normal, alpha=alpha, distortion=dist,
        radii=torch.from_numpy(radii), pixels_touched=torch.from_numpy(scores[:, 1].round().astype(np.int32)),
        contribution=torch.from_numpy(scores[:, 0]),
        error=torch.from_numpy(scores[:, 2]) if has_loss else None,
        means2d=torch.from_numpy(means2d), n_contrib=torch.from_numpy(count), stats=st.stats,
        _state=st)


def gaussian_scores(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                    opacities: torch.Tensor, colors: torch.Tensor, T_cw: ArrayLike,
                    camera: CameraModel, loss_map: ArrayLike, *, sh_degree: Optional[int] = None,
                    near: float = 0.01, far: float = 1e3) -> dict:
    """Score-manager scores of every Gaussian for one view (forward only, no autograd).

    Returns ``contribution`` ``sum_u alpha T``, ``error`` ``sum_u L(u) alpha T`` over the pixels
    ``u`` the Gaussian contributes to, and ``pixels_touched``, each ``(N,)``.
    """
    if loss_map is None:
        raise InputError("gaussian_scores: loss_map (H, W) is required (the error score needs it)")
    with torch.no_grad():
        out = rasterize_2dgs(means, quats, scales, opacities, colors, T_cw, camera,
                             sh_degree=sh_degree, loss_map=loss_map, near=near, far=far,
                             backend="numba")
    return {"contribution": out.contribution, "error": out.error,
            "pixels_touched": out.pixels_touched}
