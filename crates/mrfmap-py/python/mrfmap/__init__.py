"""mrfmap: probabilistic 3D occupancy maps from depth cameras with forward sensor models.

Build a map from numpy depth images and 4x4 camera-to-world poses with one of three engines
(``"logodds"``, OctoMap's update; ``"mrf"``, MRFMap's ray Markov random field; ``"crm"``,
confidence-rich mapping with a variance per voxel), query it at points, get its voxels as
arrays, save it, load it, and export it as PLY or OctoMap ``.bt`` / ``.ot``. Dataset folders
build whole (``build_dataset``) or, for maps larger than one machine, as tiled maps on a Dask
cluster (``mrfmap.distributed``, the optional extra ``mrfmap[distributed]``).

>>> import numpy as np, mrfmap
>>> m = mrfmap.Mapper(0.05, fx=60, fy=60, cx=39.5, cy=29.5, width=80, height=60)
>>> wall = np.full((60, 80), 2.0, dtype=np.float32)
>>> _ = m.add_frame(wall, np.eye(4))
>>> occupancy, variance = m.query(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 2.02]]))
>>> bool(occupancy[0] < 0.5 < occupancy[1])
True
"""

from ._mrfmap import Map, Mapper, build_dataset, load_map, simulate

__all__ = ["Map", "Mapper", "build_dataset", "load_map", "simulate"]
