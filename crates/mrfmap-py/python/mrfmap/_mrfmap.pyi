"""Type hints and documentation of mrfmap's compiled module."""

import os
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import numpy.typing as npt

class Mapper:
    """Builds an occupancy map from depth images of one pinhole camera.

    Camera frame: x right, y down, z forward (depth); poses are camera-to-world 4x4 rigid
    transforms. ``engine`` is ``"logodds"`` (OctoMap's update, fastest), ``"mrf"`` (MRFMap:
    keyframes that can be removed and re-posed; call ``run`` before reading the map) or
    ``"crm"`` (a pdf of ``particles`` values per voxel: mean and variance). ``noise`` is a
    ``noise.toml`` forward sensor model (bias and std polynomials, per pixel patch when
    given); without one the MRF and CRM use ``0.002 + 0.0035 z^2`` m std, no bias.
    ``max_range`` cuts longer readings, which then only clear space. MRF: ``prior`` per
    voxel, ``iterations`` the sweeps of ``run()``; every ray is a factor (module docs
    of ``mrfmap::inference::mrf``). The MRF's map leaves out voxels no ray has reached.
    ``**options`` takes the rest of ``mrfmap build``'s engine options by the same names and
    with the same defaults (``bounds``, ``tolerance``, ``work``, ``allocation``, ``damping``,
    ``ray_spacing``, ``min_evidence``, ``marking``, ``clamp``; not ``keyframes``: every frame
    given to ``add_frame`` is a keyframe). Raises ``ValueError`` for bad parameters and
    unknown options, and ``OSError`` for unreadable files.
    """

    def __init__(
        self,
        resolution: float,
        fx: float,
        fy: float,
        cx: float,
        cy: float,
        width: int,
        height: int,
        engine: str = "logodds",
        noise: Optional[os.PathLike[str] | str] = None,
        max_range: Optional[float] = None,
        particles: int = 101,
        iterations: int = 3,
        prior: float = 0.1,
        **options: Any,
    ) -> None: ...
    def add_frame(
        self,
        depth: npt.NDArray[np.float32] | npt.NDArray[np.float64] | npt.NDArray[np.uint16],
        pose: npt.NDArray[np.float64],
        depth_scale: Optional[float] = None,
        budget_ms: Optional[float] = None,
        budget_tiles: Optional[int] = None,
    ) -> int:
        """Adds a depth image of shape (height, width) taken from ``pose`` (4x4).

        Float depth is in metres (0, NaN and infinity: no measurement); uint16 depth needs
        ``depth_scale`` (units per metre). Returns the frame's id (the keyframe id for the
        MRF engine). Raises ``ValueError`` on a wrong dtype or shape, a NaN or non-rigid pose,
        and ``MemoryError`` (before any work) when the map this frame alone would make needs
        more memory than the limit (``MRFMAP_MAX_MEMORY``, else three quarters of physical
        memory; the CLI's estimate), e.g. at far too fine a resolution.

        MRF with ``budget_ms`` and/or ``budget_tiles``: the online schedule. The keyframe is
        traced whole as it arrives, then belief propagation works on the 16x16-pixel tiles
        whose inputs moved most until the budget (milliseconds from the call, tiles traced,
        the keyframe's own included) is spent; the rest waits in ``backlog`` for the next
        frames and ``refine``. The map is readable on return. ``ValueError`` for other engines.
        """
    def add_scan(
        self,
        pose: npt.NDArray[np.float64],
        directions: npt.NDArray[np.float64],
        ranges: npt.NDArray[np.float64],
        max_range: float,
    ) -> int:
        """Adds a range scan (planar laser, lidar): beam directions (N, 3) in the sensor frame,
        ranges (N,) in metres (NaN, infinity or <= 0: no return, free up to ``max_range``),
        sensor-to-world ``pose`` (4x4). Log-odds and CRM only (``ValueError`` for the MRF).
        The mapper's noise model applies in range when it has no per-patch table.
        ``MemoryError`` as for ``add_frame``.
        """
    def add_bag(
        self,
        path: os.PathLike[str] | str,
        depth_topic: str,
        fixed_frame: Optional[str] = None,
        pose_topic: Optional[str] = None,
        camera_info_topic: Optional[str] = None,
        max_pose_gap: float = 0.1,
    ) -> int:
        """Adds every posed depth image of a ROS bag (``.mcap``, ``.db3``, ROS 1 ``.bag`` or a bag
        folder), read without ROS: images of ``depth_topic`` (``sensor_msgs/Image`` 16UC1 / 32FC1
        or ``compressedDepth``), each posed in ``fixed_frame`` from ``/tf`` and ``/tf_static``
        or by ``pose_topic`` (``PoseStamped`` / ``Odometry``) at its stamp. Images without a pose
        within ``max_pose_gap`` s are skipped. The bag's CameraInfo (default: ``camera_info``
        beside the depth topic) must match this mapper's camera. The bag is read once, each
        image added as soon as its pose is known: memory holds a few images whatever the bag's
        size. Returns the images added; ``ValueError`` or ``OSError`` naming the bag and topic
        otherwise (images added before an error stay)."""
    def remove_keyframe(self, id: int) -> None:
        """MRF only: removes a keyframe; after ``run`` the map is as if it was never added."""
    def set_pose(self, id: int, pose: npt.NDArray[np.float64]) -> None:
        """MRF only: moves a keyframe to a corrected pose (after a loop closure)."""
    def run(self, iterations: Optional[int] = None) -> None:
        """MRF: belief propagation, the constructor's ``iterations`` full sweeps over every
        keyframe (default 3, the MRFMap paper's schedule); with ``iterations``, that many.
        Other engines: nothing."""
    def run_until(self, tolerance: float = 1e-3, max_sweeps: int = 100) -> Tuple[int, int, int, bool]:
        """MRF only: change-driven belief propagation until no marginal moves by more than
        ``tolerance``, re-tracing only the 16x16-pixel tiles of keyframes whose voxels moved
        since they last traced. Returns ``(sweeps, keyframe_updates, rays_traced, converged)``."""
    def refine(self, ms: Optional[float] = None, tiles: Optional[int] = None) -> Dict[str, Any]:
        """MRF only: spends idle time (``ms`` milliseconds and/or ``tiles`` traced tiles; neither:
        until settled) on the online schedule's backlog, tiles never traced (new or re-posed
        keyframes) first. Returns ``{"tiles", "own_tiles", "rays", "backlog", "settled", "ms"}``."""
    @property
    def backlog(self) -> int:
        """MRF: tiles waiting in the online schedule's backlog, as its last check found them
        (0 for the other engines)."""
    def map(self) -> Map:
        """The current map (a snapshot)."""
    def save(self, path: os.PathLike[str] | str) -> int:
        """Saves the current map to ``path`` in mrfmap's map format, straight from the live
        engine: the same file as ``map().save(path)``, but a log-odds map is written a brick at
        a time and never copied whole into memory. Returns the number of occupied voxels.
        ``OSError`` if the file cannot be written."""
    def query(
        self, points: npt.NDArray[np.float64]
    ) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Occupancy and variance at (N, 3) points, as ``Map.query``, read from the live engine
        (no copy of the map)."""
    def query_points(self, points: npt.NDArray[np.float64], unknown: float = 0.5) -> Dict[str, npt.NDArray[Any]]:
        """``Map.query_points`` on the live engine."""
    def query_segments(
        self,
        starts: npt.NDArray[np.float64],
        ends: npt.NDArray[np.float64],
        unknown: float = 0.5,
        k: float = 2.0,
        threshold: float = 0.5,
    ) -> Dict[str, npt.NDArray[Any]]:
        """``Map.query_segments`` on the live engine."""
    def query_boxes(
        self,
        mins: npt.NDArray[np.float64],
        maxs: npt.NDArray[np.float64],
        unknown: float = 0.5,
        threshold: float = 0.5,
    ) -> Dict[str, npt.NDArray[Any]]:
        """``Map.query_boxes`` on the live engine."""
    def query_polyline(
        self, points: npt.NDArray[np.float64], unknown: float = 0.5, k: float = 2.0, threshold: float = 0.5
    ) -> Dict[str, Any]:
        """``Map.query_polyline`` on the live engine."""
    @property
    def engine(self) -> str: ...
    @property
    def resolution(self) -> float: ...

class Map:
    """A finished map: per known voxel an occupancy probability and a variance."""

    def query(
        self, points: npt.NDArray[np.float64]
    ) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """Occupancy and variance of the voxels holding (N, 3) points; NaN where unknown.

        Engines without a variance (log-odds, MRF) report ``p (1 - p)``.
        Raises ``ValueError`` for a wrong shape or NaN points.
        """
    def query_points(self, points: npt.NDArray[np.float64], unknown: float = 0.5) -> Dict[str, npt.NDArray[Any]]:
        """Per (N, 3) point: ``occupancy`` (``unknown`` where the map knows nothing), ``std``
        (the engine's own for CRM, ``sqrt(p (1 - p))`` otherwise) and ``known`` (bool)."""
    def query_segments(
        self,
        starts: npt.NDArray[np.float64],
        ends: npt.NDArray[np.float64],
        unknown: float = 0.5,
        k: float = 2.0,
        threshold: float = 0.5,
    ) -> Dict[str, npt.NDArray[Any]]:
        """Per segment ``starts[i] -> ends[i]`` (both (N, 3)), over the voxels it crosses with
        positive length (unknown ones at ``unknown``): ``p_free`` = prod(1 - p),
        ``expected_occupied`` = sum(p), ``p_free_lcb`` = prod(1 - min(1, p + k std)) (a lower
        confidence bound), ``first_hit`` (N, 3): centre of the first voxel above ``threshold``
        (NaN if none), ``voxels`` and ``unknown`` counts. Runs in parallel without the GIL."""
    def query_boxes(
        self,
        mins: npt.NDArray[np.float64],
        maxs: npt.NDArray[np.float64],
        unknown: float = 0.5,
        threshold: float = 0.5,
    ) -> Dict[str, npt.NDArray[Any]]:
        """Per box ``mins[i]`` to ``maxs[i]``, over the voxels overlapping it: ``max_occupancy``,
        ``p_free`` (all voxels free), and ``occupied``, ``free``, ``unknown`` counts."""
    def query_polyline(
        self, points: npt.NDArray[np.float64], unknown: float = 0.5, k: float = 2.0, threshold: float = 0.5
    ) -> Dict[str, Any]:
        """One path through (K, 3) waypoints, as ``query_segments`` over the union of the legs'
        voxels (each counted once): ``p_free``, ``expected_occupied``, ``p_free_lcb`` (floats),
        ``first_hit`` (a list of 3 floats or None), ``voxels``, ``unknown`` (ints)."""
    def voxels(
        self,
    ) -> Tuple[npt.NDArray[np.float64], npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """All voxels: centres (N, 3) in metres, occupancy (N,), variance (N,)."""
    def save(self, path: os.PathLike[str] | str) -> None:
        """Saves in mrfmap's map format (readable by ``load_map`` and the ``mrfmap`` command)."""
    def export_ply(self, path: os.PathLike[str] | str, occupied_only: bool = False) -> int:
        """Binary PLY of voxel centres with occupancy (and variance); returns the vertex count.
        ``ValueError`` if no voxel would be written."""
    def export_bt(self, path: os.PathLike[str] | str) -> None:
        """OctoMap ``.bt`` (occupied above 0.5 / free, pruned). ``ValueError`` if empty."""
    def export_ot(self, path: os.PathLike[str] | str) -> None:
        """OctoMap ``.ot`` (log-odds per node). ``ValueError`` if empty."""
    @property
    def resolution(self) -> float: ...
    @property
    def engine(self) -> str: ...
    @property
    def occupied_count(self) -> int: ...
    def __len__(self) -> int: ...

def load_map(path: os.PathLike[str] | str) -> Map:
    """Loads a map file written by ``mrfmap build`` or ``Map.save``, or a tiled map's folder
    (every tile stitched into one map; the memory limit applies to their sum)."""

def simulate(scene: os.PathLike[str] | str, out_dir: os.PathLike[str] | str, seed: int = 0) -> int:
    """Renders a scene file into a dataset folder, as ``mrfmap simulate``; returns the frames."""

def build_dataset(dataset: os.PathLike[str] | str, **options: Any) -> Map:
    """Builds every frame of a dataset folder into one map. Options, as ``mrfmap build``'s:
    ``resolution`` (required), ``engine`` (``"logodds"``, ``"mrf"``, ``"crm"``),
    ``max_range``, ``bounds`` ([xmin, ymin, zmin, xmax, ymax, zmax]), ``noise`` (a
    ``noise.toml``), ``threads``; MRF: ``iterations``, ``tolerance``, ``work``, ``prior``,
    ``allocation``, ``keyframes``, ``damping``, ``ray_spacing``, ``min_evidence``; CRM:
    ``particles``; log-odds: ``marking``, ``clamp`` ((min, max)). Each means what the flag
    of the same name means, with the same default. Tiled builds: ``mrfmap.distributed.build``."""

def _plan_tiles(dataset: str, frames: Optional[List[int]] = None, **options: Any) -> List[Tuple[Tuple[int, int, int], List[int]]]: ...
def _frame_count(dataset: str, **options: Any) -> int: ...
def _tile_estimate(dataset: str, key: Tuple[int, int, int], frames: List[int], **options: Any) -> float: ...
def _build_tile(dataset: str, out_dir: str, key: Tuple[int, int, int], frames: List[int], **options: Any) -> Dict[str, Any]: ...
def _write_tile_index(dataset: str, out_dir: str, entries: List[Dict[str, Any]], **options: Any) -> int: ...
