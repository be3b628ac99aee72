"""The 2D Gaussian (surfel) map as a dataclass of row-aligned tensors.

Every field has one row per Gaussian. Geometry is in the world frame (metres):

* ``means`` (N, 3) float32 centre; ``quats`` (N, 4) float32 rotation ``(x, y, z, w)`` (not necessarily
  normalised; the surfel's tangent axes are the first two columns of its rotation, its normal the
  third); ``log_scales`` (N, 2) float32 log of the two in-plane standard deviations (m);
  ``opacity_logits`` (N,) float32 (opacity = sigmoid); ``sh`` (N, (d+1)^2, 3) float32 colour SH
  coefficients (DC band first, 3DGS convention ``rgb = 0.5 + C0 * sh[:, 0]``).
* Score manager state: ``kf_id`` (N,) int64 ID(g), the stamp (ns) of the keyframe where the Gaussian's
  contribution is highest; ``id_score`` (N,) float32 that best per-keyframe contribution;
  ``win_c`` / ``win_e`` (N, K) float32 the contribution / error of the latest render of each of the K
  local-window keyframe slots (``S_C`` = row sum, ``S_E`` = row max, see :mod:`.scores`);
  ``score_since`` (N,) int64 the training-render count when its scoring (re)started; ``stable`` (N,) bool.
* Sparse-Adam state: ``m_<param>`` / ``v_<param>`` first and second moments of each parameter and
  ``adam_step`` (N,) int32 per-row step counts.

All operations (index, concat, remove, rigid and similarity transforms) are vectorised over rows.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Iterable, Sequence

import numpy as np
import torch

from ..geometry import quat_to_rotmat

SH_C0 = 0.28209479177387814

PARAM_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")
SCORE_FIELDS = ("kf_id", "id_score", "win_c", "win_e", "score_since", "stable")
ADAM_FIELDS = tuple(f"m_{p}" for p in PARAM_FIELDS) + tuple(f"v_{p}" for p in PARAM_FIELDS) + ("adam_step",)
ALL_FIELDS = PARAM_FIELDS + SCORE_FIELDS + ADAM_FIELDS


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """RGB in [0, 1] -> DC SH coefficient (3DGS convention)."""
    return (rgb - 0.5) / SH_C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return dc * SH_C0 + 0.5


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a * b`` of ``(..., 4)`` quaternions in ``(x, y, z, w)`` order."""
    ax, ay, az, aw = a.unbind(-1)
    bx, by, bz, bw = b.unbind(-1)
    return torch.stack([aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw,
                        aw * bw - ax * bx - ay * by - az * bz], -1)


@dataclass
class GaussianMap:
    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh: torch.Tensor
    kf_id: torch.Tensor
    id_score: torch.Tensor
    win_c: torch.Tensor
    win_e: torch.Tensor
    score_since: torch.Tensor
    stable: torch.Tensor
    m_means: torch.Tensor
    m_quats: torch.Tensor
    m_log_scales: torch.Tensor
    m_opacity_logits: torch.Tensor
    m_sh: torch.Tensor
    v_means: torch.Tensor
    v_quats: torch.Tensor
    v_log_scales: torch.Tensor
    v_opacity_logits: torch.Tensor
    v_sh: torch.Tensor
    adam_step: torch.Tensor

    # ------------------------------------------------------------------ construction
    @staticmethod
    def create(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor,
               opacity_logits: torch.Tensor, sh: torch.Tensor, kf_id: int | torch.Tensor,
               score_since: int = 0, window: int = 8) -> "GaussianMap":
        """New Gaussians with zeroed scores (unstable) and zeroed optimiser state."""
        n = means.shape[0]
        dev = means.device
        f32 = dict(dtype=torch.float32, device=dev)
        kid = torch.as_tensor(kf_id, dtype=torch.int64, device=dev)
        kid = kid.expand(n).clone() if kid.ndim == 0 else kid.clone()
        params = dict(means=means.to(**f32).contiguous(), quats=quats.to(**f32).contiguous(),
                      log_scales=log_scales.to(**f32).contiguous(),
                      opacity_logits=opacity_logits.to(**f32).reshape(n).contiguous(),
                      sh=sh.to(**f32).contiguous())
        for k, shape in (("means", (n, 3)), ("quats", (n, 4)), ("log_scales", (n, 2))):
            if tuple(params[k].shape) != shape:
                raise ValueError(f"GaussianMap.{k} has shape {tuple(params[k].shape)}, expected {shape}")
        if params["sh"].ndim != 3 or params["sh"].shape[0] != n or params["sh"].shape[2] != 3:
            raise ValueError(f"GaussianMap.sh has shape {tuple(params['sh'].shape)}, expected (N, K, 3)")
        kw = dict(params)
        kw.update(kf_id=kid, id_score=torch.zeros(n, **f32), win_c=torch.zeros(n, int(window), **f32),
                  win_e=torch.zeros(n, int(window), **f32),
                  score_since=torch.full((n,), int(score_since), dtype=torch.int64, device=dev),
                  stable=torch.zeros(n, dtype=torch.bool, device=dev),
                  adam_step=torch.zeros(n, dtype=torch.int32, device=dev))
        for p in PARAM_FIELDS:
            kw[f"m_{p}"] = torch.zeros_like(params[p])
            kw[f"v_{p}"] = torch.zeros_like(params[p])
        return GaussianMap(**kw)

    @staticmethod
    def empty(sh_degree: int = 0, window: int = 8, device: str | torch.device = "cpu") -> "GaussianMap":
        k = (sh_degree + 1) ** 2
        z = lambda *s: torch.zeros(s, dtype=torch.float32, device=device)  # noqa: E731
        return GaussianMap.create(z(0, 3), z(0, 4), z(0, 2), z(0), z(0, k, 3),
                                  torch.zeros(0, dtype=torch.int64, device=device), window=window)

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(self.sh.shape[1] ** 0.5)) - 1

    @property
    def device(self) -> torch.device:
        return self.means.device

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def nbytes(self) -> int:
        return int(sum(t.element_size() * t.numel() for t in self.tensors().values()))

    def finite_rows(self) -> torch.Tensor:
        """Bool (N,): Gaussians whose parameters (means, quats, scales, opacity, SH) are all finite."""
        n = len(self)
        return (torch.isfinite(self.means).all(1) & torch.isfinite(self.log_scales).all(1)
                & torch.isfinite(self.quats).all(1)
                & torch.isfinite(self.opacity_logits.reshape(n, -1)).all(1)
                & torch.isfinite(self.sh.reshape(n, -1)).all(1))

    def index(self, idx: torch.Tensor) -> "GaussianMap":
        """Rows selected by a bool mask or an index tensor (copies)."""
        return GaussianMap(**{k: v[idx] for k, v in self.tensors().items()})

    def remove(self, mask: torch.Tensor) -> "GaussianMap":
        """The map without the rows where ``mask`` (bool, N) is True."""
        return self.index(~mask)

    @staticmethod
    def concat(maps: Sequence["GaussianMap"]) -> "GaussianMap":
        maps = [m for m in maps if m is not None]
        if not maps:
            raise ValueError("concat needs at least one map")
        if len(maps) == 1:
            return maps[0]
        names = [f.name for f in fields(GaussianMap)]
        return GaussianMap(**{k: torch.cat([getattr(m, k) for m in maps], 0) for k in names})

    def to(self, device: str | torch.device) -> "GaussianMap":
        return GaussianMap(**{k: v.to(device) for k, v in self.tensors().items()})

    def clone(self) -> "GaussianMap":
        return GaussianMap(**{k: v.clone() for k, v in self.tensors().items()})

    # ------------------------------------------------------------------ numpy I/O (bit-exact)
    def to_numpy(self) -> dict[str, np.ndarray]:
        return {k: v.detach().cpu().numpy().copy() for k, v in self.tensors().items()}

    @staticmethod
    def from_numpy(d: dict, device: str | torch.device = "cpu") -> "GaussianMap":
        missing = [k for k in ALL_FIELDS if k not in d]
        if missing:
            raise ValueError(f"Gaussian record lacks fields {missing}")
        return GaussianMap(**{k: torch.from_numpy(np.array(d[k], copy=True)).to(device) for k in ALL_FIELDS})

    # ------------------------------------------------------------------ derived quantities
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def normals(self) -> torch.Tensor:
        """(N, 3) unit surfel normals in the world frame (third rotation column)."""
        return quat_to_rotmat(self.quats)[..., :, 2]

    def rgb(self) -> torch.Tensor:
        """(N, 3) view-independent colour (DC band) in [0, 1] (unclamped)."""
        return sh_dc_to_rgb(self.sh[:, 0])

    # ------------------------------------------------------------------ rigid and similarity motion
    def apply_rigid(self, T: torch.Tensor, rows: torch.Tensor | None = None) -> None:
        """In place: move Gaussians rigidly by world-frame transforms.

        ``T``: (4, 4) for all ``rows`` or (M, 4, 4) one per selected row; ``rows``: bool mask or
        indices (None = all). Means are transformed, rotations left-multiplied, SH bands >= 1
        rotated (:func:`~vings_core.render.sh.rotate_sh`: the colour travels with the Gaussian);
        Adam first moments of means, quats and SH are rotated along (they are expressed in the
        world frame); second moments are kept.
        """
        self.apply_similarity(T, rows, None)

    def apply_similarity(self, T: torch.Tensor, rows: torch.Tensor | None = None,
                         scale: torch.Tensor | None = None) -> None:
        """In place: move Gaussians by world-frame similarities ``x -> s R x + t``.

        ``T``: (4, 4) ``[[s R, t], [0, 1]]`` for all ``rows`` or (M, 4, 4) one per selected row;
        ``scale``: the ``s`` of each (a scalar or (M,); None: 1, ``T`` rigid, as
        :meth:`apply_rigid`). Means are transformed, rotations left-multiplied by ``R``, SH bands
        >= 1 rotated by ``R``, in-plane scales multiplied by ``s`` (``log s`` added to the
        log-scales). Adam first moments of means, quats and SH are rotated by ``R`` (not scaled:
        Adam's step ``m / sqrt(v)`` is invariant to a common gradient scale); second moments kept.
        """
        sel = torch.arange(len(self), device=self.device) if rows is None else rows
        if sel.dtype == torch.bool:
            sel = sel.nonzero()[:, 0]
        if sel.numel() == 0:
            return
        T = T.to(torch.float64)
        L = T[..., :3, :3]
        t = T[..., :3, 3]
        mu = self.means[sel].to(torch.float64)
        if T.ndim == 2:
            L = L.expand(len(sel), 3, 3)
            t = t.expand(len(sel), 3)
        mu = (L @ mu[:, :, None])[:, :, 0] + t
        s = None if scale is None else torch.as_tensor(scale, dtype=torch.float64).expand(len(sel))
        R = L if s is None else L / s[:, None, None]
        from ..geometry import rotmat_to_quat
        qR = rotmat_to_quat(R)
        q = quat_multiply(qR, self.quats[sel].to(torch.float64))
        mm = (R @ self.m_means[sel].to(torch.float64)[:, :, None])[:, :, 0]
        # q -> qR q is the orthogonal linear map L(qR), so dL/dq (and its Adam first moment) maps by
        # the same L; the second moments (per-component squares) cannot be rotated and are kept
        mq = quat_multiply(qR, self.m_quats[sel].to(torch.float64))
        self.means[sel] = mu.to(torch.float32)
        self.quats[sel] = q.to(torch.float32)
        self.m_means[sel] = mm.to(torch.float32)
        self.m_quats[sel] = mq.to(torch.float32)
        if s is not None:
            self.log_scales[sel] = (self.log_scales[sel].to(torch.float64) + torch.log(s)[:, None]).to(torch.float32)
        if self.sh.shape[1] > 1:
            from ..render.sh import rotate_sh
            self.sh[sel] = rotate_sh(self.sh[sel], R)
            self.m_sh[sel] = rotate_sh(self.m_sh[sel], R)

def field_names() -> Iterable[str]:
    return ALL_FIELDS
