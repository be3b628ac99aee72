"""Online 2D Gaussian map (paper section "2D Gaussian Map"): see docs/mapping.md.

Public API::

    from vings_core.mapping import Mapper, MapperConfig
    m = Mapper(MapperConfig(), device="cpu")
    m.add_keyframe(kf); m.train(); m.refine_poses()
    m.render(T_wc, camera)          # numpy color / depth / normal / alpha
    m.keyframe_poses(); m.set_keyframe_poses({stamp: T_wc})
    m.save_ply(path); m.save_checkpoint(path); Mapper.load_checkpoint(path, config)
    m.apply_increments({stamp: C})  # world-frame Sim(3) corrections; Gaussians follow
"""
from .config import MapperConfig, RefineMode, RefineSolver
from .gaussians import GaussianMap
from .mapper import Mapper
from .ply import read_ply, write_ply

__all__ = ["Mapper", "MapperConfig", "RefineMode", "RefineSolver", "GaussianMap", "read_ply", "write_ply"]
