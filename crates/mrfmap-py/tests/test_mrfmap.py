"""Tests of the Python bindings: a wall seen head-on, every engine, keyframe edits, files, and
every kind of bad input raising ValueError (never crashing the interpreter)."""

import math
import os

import numpy as np
import pytest

import mrfmap

CAM = dict(fx=60.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60)


def wall(z=2.02):
    # Inside a 0.05 m voxel, not on its face: on a face the MRF lets the nearer voxel explain
    # the readings and leaves the one behind it at the prior.
    return np.full((60, 80), z, dtype=np.float32)


def pose(x=0.0):
    p = np.eye(4)
    p[0, 3] = x
    return p


@pytest.mark.parametrize("engine", ["logodds", "mrf", "crm"])
def test_wall_is_occupied_and_space_in_front_free(engine):
    m = mrfmap.Mapper(0.05, engine=engine, particles=21, **CAM)
    for i in range(3):
        m.add_frame(wall(), pose(0.01 * i))
    m.run()
    # 0.15 m in front of the wall: inside every engine's allocation (the MRF's is a band).
    occ, var = m.query(np.array([[0.0, 0.0, 1.85], [0.0, 0.0, 2.02], [0.0, 0.0, 50.0]]))
    assert occ[0] < 0.5 < occ[1]
    assert math.isnan(occ[2]) and math.isnan(var[2])
    assert np.all(var[:2] >= 0) and np.all(var[:2] <= 0.25)
    centres, o, v = m.map().voxels()
    assert centres.shape == (len(o), 3) and o.dtype == np.float32 and len(v) == len(o)
    assert m.engine == engine and m.resolution == 0.05


def test_uint16_depth_and_float64_depth_agree():
    a = mrfmap.Mapper(0.05, **CAM)
    b = mrfmap.Mapper(0.05, **CAM)
    a.add_frame(np.full((60, 80), 2020, dtype=np.uint16), np.eye(4), depth_scale=1000.0)
    b.add_frame(wall().astype(np.float64), np.eye(4))
    assert len(a.map()) == len(b.map()) and a.map().occupied_count == b.map().occupied_count


def test_mrf_remove_equals_never_added_and_repose():
    m = mrfmap.Mapper(0.05, engine="mrf", **CAM)
    keep = m.add_frame(wall(), pose())
    extra = m.add_frame(wall(1.52), pose())  # a conflicting reading
    m.run(5)
    m.remove_keyframe(extra)
    m.run(100)
    ref = mrfmap.Mapper(0.05, engine="mrf", **CAM)
    ref.add_frame(wall(), pose())
    ref.run(100)
    pts = np.array([[0.0, 0.0, 1.52], [0.0, 0.0, 2.02]])
    # Loopy belief propagation can have more than one fixed point: after the conflicting
    # reading the damped updates settle 2e-3 from the never-added map's (tests/mrf.rs checks
    # removal to 1e-5 on a scene without such a conflict).
    np.testing.assert_allclose(m.query(pts)[0], ref.query(pts)[0], atol=5e-3)
    m.set_pose(keep, pose(0.5))
    sweeps, updates, rays, converged = m.run_until(1e-3, 200)
    assert converged and updates >= 1 and rays >= 60 * 80 and sweeps >= 1
    with pytest.raises(ValueError, match="tolerance"):
        m.run_until(0.0)
    with pytest.raises(ValueError, match="keyframe"):
        m.remove_keyframe(12345)


def test_mrf_online_budget_backlog_and_refine():
    m = mrfmap.Mapper(0.05, engine="mrf", **CAM)
    # 80x60 pixels: 20 tiles per keyframe, traced whole whatever the budget.
    for i in range(4):
        m.add_frame(wall(2.02 + 0.01 * i), pose(0.02 * i), budget_tiles=22)
    assert m.backlog > 0
    occ, _ = m.query(np.array([[0.0, 0.0, 1.85], [0.0, 0.0, 2.02]]))
    assert occ[0] < 0.5 < occ[1]  # readable at once
    r = m.refine(tiles=5)
    assert r["tiles"] <= 5 and r["own_tiles"] == 0
    r = m.refine()
    assert r["settled"] and r["backlog"] == 0 and m.backlog == 0
    assert set(r) == {"tiles", "own_tiles", "rays", "backlog", "settled", "ms"}
    m.add_frame(wall(), pose(0.1), budget_ms=5000.0)
    with pytest.raises(ValueError, match="budget"):
        m.refine(ms=-1.0)
    lo = mrfmap.Mapper(0.05, **CAM)
    with pytest.raises(ValueError, match="mrf"):
        lo.add_frame(wall(), pose(), budget_ms=10.0)
    with pytest.raises(ValueError, match="mrf"):
        lo.refine()
    assert lo.backlog == 0


def test_files_round_trip(tmp_path):
    m = mrfmap.Mapper(0.05, engine="crm", particles=15, **CAM)
    m.add_frame(wall(), np.eye(4))
    mp = m.map()
    mp.save(tmp_path / "w.mrfmap")
    back = mrfmap.load_map(str(tmp_path / "w.mrfmap"))
    assert len(back) == len(mp) and back.engine == "crm"
    pts = mp.voxels()[0]
    np.testing.assert_array_equal(back.query(pts)[0], mp.query(pts)[0])
    assert mp.export_ply(tmp_path / "w.ply", occupied_only=True) == mp.occupied_count
    mp.export_bt(tmp_path / "w.bt")
    mp.export_ot(tmp_path / "w.ot")
    assert (tmp_path / "w.bt").read_bytes().startswith(b"# Octomap OcTree binary file")


def test_mapper_saves_the_file_its_map_would(tmp_path):
    for engine in ("logodds", "crm"):
        m = mrfmap.Mapper(0.05, engine=engine, particles=15, **CAM)
        m.add_frame(wall(), np.eye(4))
        whole, live = tmp_path / f"{engine}-whole.mrfmap", tmp_path / f"{engine}-live.mrfmap"
        mp = m.map()
        mp.save(whole)
        assert m.save(live) == mp.occupied_count > 0
        assert live.read_bytes() == whole.read_bytes(), engine
        with pytest.raises(OSError):
            m.save(tmp_path / "no-such-folder" / "m.mrfmap")


def test_bad_input_raises_value_error(tmp_path):
    m = mrfmap.Mapper(0.05, **CAM)
    cases = [
        (lambda: m.add_frame(np.zeros((10, 10), np.float32), np.eye(4)), "shape"),
        (lambda: m.add_frame(wall().astype(np.int32), np.eye(4)), "dtype"),
        (lambda: m.add_frame([[1.0]], np.eye(4)), "depth"),
        (lambda: m.add_frame(np.zeros((60, 80), np.uint16), np.eye(4)), "depth_scale"),
        (lambda: m.add_frame(wall(), np.full((4, 4), np.nan)), "NaN"),
        (lambda: m.add_frame(wall(), np.eye(3)), "4x4"),
        (lambda: m.add_frame(wall(), 2 * np.eye(4)), "last row"),
        (lambda: m.add_frame(wall(), np.diag([2.0, 1.0, 1.0, 1.0])), "rotation"),
        (lambda: m.query(np.zeros((3, 2))), "points"),
        (lambda: m.query(np.array([[np.nan, 0.0, 0.0]])), "NaN"),
        (lambda: m.remove_keyframe(0), "mrf"),
        (lambda: mrfmap.Mapper(0.05, engine="octree", **CAM), "unknown engine"),
        (lambda: mrfmap.Mapper(-1.0, **CAM), "resolution"),
        (lambda: mrfmap.Mapper(0.05, engine="crm", particles=1, **CAM), "particles"),
        (lambda: m.map().export_bt(tmp_path / "empty.bt"), "empty"),
        (lambda: m.map().export_ply(tmp_path / "empty.ply"), "nothing to export"),
    ]
    for call, needle in cases:
        with pytest.raises(ValueError, match=needle):
            call()
    assert not (tmp_path / "empty.bt").exists() and not (tmp_path / "empty.ply").exists()
    with pytest.raises(OSError):
        mrfmap.load_map(tmp_path / "missing.mrfmap")


def test_module_docstring_example():
    import doctest

    assert doctest.testmod(mrfmap, raise_on_error=True).attempted > 0


@pytest.mark.parametrize("engine", ["logodds", "crm"])
def test_range_scan_ring(engine):
    m = mrfmap.Mapper(0.05, engine=engine, particles=21, **CAM)
    angles = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    dirs = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    ranges = np.full(720, 2.0)
    ranges[::10] = np.nan  # no return
    pose = np.eye(4)
    pose[2, 3] = 0.025
    for _ in range(3):
        m.add_scan(pose, dirs, ranges, 4.0)
    # Along beams 5 and 365 (which return): free at 1 m, occupied just before 2 m.
    pts = [[r * np.cos(angles[k]), r * np.sin(angles[k]), 0.025] for k, r in [(5, 1.0), (5, 1.999), (365, 1.999)]]
    occ, _ = m.query(np.array(pts))
    assert occ[0] < 0.5 < occ[1] and occ[2] > 0.5
    # Beam 0 returned nothing: free out to the 4 m range, past the ring.
    far, _ = m.query(np.array([[3.0, 0.0, 0.025]]))
    assert far[0] < 0.5


def test_range_scan_bad_input():
    m = mrfmap.Mapper(0.05, **CAM)
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="ranges"):
        m.add_scan(np.eye(4), dirs, np.array([1.0]), 4.0)
    with pytest.raises(ValueError, match="directions"):
        m.add_scan(np.eye(4), np.zeros((2, 2)), np.array([1.0, 1.0]), 4.0)
    with pytest.raises(ValueError, match="beam 0"):
        m.add_scan(np.eye(4), np.zeros((2, 3)), np.array([1.0, 1.0]), 4.0)
    with pytest.raises(ValueError, match="maximum range"):
        m.add_scan(np.eye(4), dirs, np.array([1.0, 1.0]), -1.0)
    mrf = mrfmap.Mapper(0.05, engine="mrf", **CAM)
    with pytest.raises(ValueError, match="depth images only"):
        mrf.add_scan(np.eye(4), dirs, np.array([1.0, 1.0]), 4.0)


@pytest.mark.parametrize("engine", ["logodds", "mrf", "crm"])
def test_path_queries_with_confidence(engine):
    m = mrfmap.Mapper(0.05, engine=engine, particles=21, **CAM)
    for i in range(3):
        m.add_frame(wall(), pose(0.01 * i))
    m.run()
    # A path to just before the wall, one through it, one far beside the camera (unknown).
    starts = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [50.0, 0.0, 0.0]])
    ends = np.array([[0.0, 0.0, 1.9], [0.0, 0.0, 2.3], [51.0, 0.0, 0.0]])
    live = m.query_segments(starts, ends, k=1.0)
    snap = m.map().query_segments(starts, ends, k=1.0)
    for key in ["p_free", "p_free_lcb", "expected_occupied", "voxels", "unknown"]:
        np.testing.assert_array_equal(live[key], snap[key])
    # Every engine's free space is short of certain (and the MRF's band leaves part of the
    # first path unknown), but through the wall is far less likely free than up to it.
    assert live["p_free"][0] > 100 * live["p_free"][1]
    assert np.all(live["p_free_lcb"] <= live["p_free"])
    assert abs(live["first_hit"][1][2] - 2.025) < 1e-9 and np.isnan(live["first_hit"][0]).all()
    assert live["unknown"][2] == live["voxels"][2] == 20 and abs(live["p_free"][2] - 0.5**20) < 1e-12
    # There and back again: the polyline counts each voxel once, like the one-way segment.
    # (Ends inside voxels: at a face, rounding may touch the next voxel for 1e-16 m.)
    there_and_back = m.query_polyline(np.array([[0.0, 0.0, 1.01], [0.0, 0.0, 2.31], [0.0, 0.0, 1.01]]), k=1.0)
    one_way = m.query_segments(np.array([[0.0, 0.0, 1.01]]), np.array([[0.0, 0.0, 2.31]]), k=1.0)
    assert there_and_back["voxels"] == one_way["voxels"][0] and there_and_back["p_free"] == one_way["p_free"][0]
    assert abs(there_and_back["first_hit"][2] - 2.025) < 1e-9
    pts = m.query_points(np.array([[0.0, 0.0, 2.02], [9.0, 9.0, 9.0]]), unknown=0.25)
    assert list(pts["known"]) == [True, False] and pts["occupancy"][1] == 0.25
    boxes = m.map().query_boxes(np.array([[-0.1, -0.1, 1.99]]), np.array([[0.1, 0.1, 2.04]]))
    assert boxes["occupied"][0] > 0 and boxes["p_free"][0] < 0.5
    with pytest.raises(ValueError, match="same number of rows"):
        m.query_segments(starts, ends[:2])
    # Far endpoints: refused before any walking (they ran for minutes, or overflowed to "free").
    with pytest.raises(ValueError, match="segment 0: .*clip it"):
        m.query_segments(np.array([[-1e9, 0.0, 0.0]]), np.array([[1e9, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="clip it"):
        m.map().query_polyline(np.array([[-1e308, 0.0, 0.0], [1e308, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="unknown"):
        m.query_points(starts, unknown=1.5)
    with pytest.raises(ValueError, match="min < max"):
        m.query_boxes(np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 1.0]]))


def write_wall_bag(path, depths, xs):
    """An MCAP bag of depth images (32FC1) with CameraInfo and /tf map -> cam, written by the
    pure-Python `rosbags` package."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        ci = w.add_connection("/cam/depth", "sensor_msgs/msg/Image", typestore=ts)
        cc = w.add_connection("/cam/camera_info", "sensor_msgs/msg/CameraInfo", typestore=ts)
        ct = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=ts)
        for i, (depth, x) in enumerate(zip(depths, xs)):
            stamp = T["builtin_interfaces/msg/Time"](sec=i + 1, nanosec=0)
            hdr = T["std_msgs/msg/Header"](stamp=stamp, frame_id="cam")
            k = np.array([CAM["fx"], 0, CAM["cx"], 0, CAM["fy"], CAM["cy"], 0, 0, 1], dtype=np.float64)
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            info = T["sensor_msgs/msg/CameraInfo"](header=hdr, height=60, width=80, distortion_model="", d=np.zeros(0), k=k, r=np.eye(3).flatten(), p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)
            V3, Q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
            tr = T["geometry_msgs/msg/Transform"](translation=V3(x=x, y=0.0, z=0.0), rotation=Q(x=0.0, y=0.0, z=0.0, w=1.0))
            tfs = T["geometry_msgs/msg/TransformStamped"](header=T["std_msgs/msg/Header"](stamp=stamp, frame_id="map"), child_frame_id="cam", transform=tr)
            img = T["sensor_msgs/msg/Image"](header=hdr, height=60, width=80, encoding="32FC1", is_bigendian=0, step=320, data=depth.astype("<f4").view(np.uint8).reshape(-1))
            ns = (i + 1) * 10**9
            w.write(cc, ns, ts.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
            w.write(ct, ns, ts.serialize_cdr(T["tf2_msgs/msg/TFMessage"](transforms=[tfs]), "tf2_msgs/msg/TFMessage"))
            w.write(ci, ns, ts.serialize_cdr(img, "sensor_msgs/msg/Image"))


@pytest.mark.parametrize("engine", ["logodds", "crm"])
def test_add_bag_equals_add_frame(tmp_path, engine):
    depths, xs = [wall(), wall(2.1)], [0.0, 0.02]
    write_wall_bag(tmp_path / "bag", depths, xs)
    a = mrfmap.Mapper(0.05, engine=engine, particles=21, **CAM)
    assert a.add_bag(tmp_path / "bag", "/cam/depth", fixed_frame="map") == 2
    b = mrfmap.Mapper(0.05, engine=engine, particles=21, **CAM)
    for d, x in zip(depths, xs):
        b.add_frame(d, pose(x))
    pts = np.array([[0.0, 0.0, z] for z in np.arange(1.0, 2.3, 0.05)])
    np.testing.assert_array_equal(a.query(pts)[0], b.query(pts)[0])
    with pytest.raises(ValueError, match="camera"):
        mrfmap.Mapper(0.05, fx=61.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60).add_bag(tmp_path / "bag", "/cam/depth", fixed_frame="map")
    with pytest.raises(ValueError, match="does not connect|no image"):
        a.add_bag(tmp_path / "bag", "/cam/depth", fixed_frame="world")


@pytest.mark.parametrize("engine", ["logodds", "crm"])
def test_a_frame_or_scan_too_large_for_memory_is_refused_before_any_work(engine):
    # A nanometre voxel: the CLI's estimate says petabytes; Python refuses as it does, where
    # it once grew to 23.6 GB and was killed. (The MRF allocates around depth points only:
    # its estimate at 1e-9 m is small, and rightly so.)
    m = mrfmap.Mapper(1e-9, engine=engine, particles=21, **CAM)
    with pytest.raises(MemoryError, match="memory"):
        m.add_frame(wall(), pose())
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(MemoryError, match="memory"):
        m.add_scan(pose(), dirs, np.array([2.0, 2.0]), 4.0)
    assert m.map().voxels()[1].size == 0
    # The same frame at a sane resolution goes in.
    ok = mrfmap.Mapper(0.05, engine=engine, particles=21, **CAM)
    ok.add_frame(wall(), pose())


def small_floor(tmp_path):
    """A 2 x 2-room floor (6.4 m rooms) seen along a path, rendered into a dataset folder by
    the floor generator the benchmark uses."""
    import pathlib
    import subprocess
    import sys

    script = pathlib.Path(__file__).resolve().parents[3] / "bench" / "floor_scene.py"
    scene = tmp_path / "floor.toml"
    subprocess.run(
        [sys.executable, str(script), str(scene), "--rooms", "2", "--room", "6.4", "--frames", "40",
         "--width", "64", "--height", "48"],
        check=True,
    )
    dataset = tmp_path / "floor"
    assert mrfmap.simulate(scene, dataset) == 40
    return dataset


def test_mapper_takes_the_build_options():
    m = mrfmap.Mapper(0.05, engine="logodds", clamp=(0.3, 0.8), bounds=[-1, -1, 0, 1, 1, 3], **CAM)
    m.add_frame(wall(), pose())
    centres, occ, _ = m.map().voxels()
    assert occ.size > 0 and occ.min() >= 0.3 - 1e-6 and occ.max() <= 0.8 + 1e-6
    # Bounds hold to the voxel: no centre beyond the box by more than half a voxel (the wall
    # itself, 2.7 m wide, would reach 1.35 m).
    assert np.all(centres[:, 2] < 3.0) and np.all(np.abs(centres[:, :2]) <= 1.025 + 1e-9)
    for bad, message in [(dict(colour="red"), "unknown option"), (dict(keyframes="auto"), "every frame"),
                         (dict(marking="ray"), "unknown marking")]:
        with pytest.raises(ValueError, match=message):
            mrfmap.Mapper(0.05, **bad, **CAM)


def test_build_options_mean_what_the_flags_mean(tmp_path, monkeypatch):
    dataset = small_floor(tmp_path)
    plain = mrfmap.build_dataset(dataset, resolution=0.2)
    # Tighter clamping bounds change every voxel's probability, not which voxels exist.
    clamped = mrfmap.build_dataset(dataset, resolution=0.2, clamp=(0.3, 0.8), marking="walk")
    assert len(clamped) == len(plain) > 0
    occ = clamped.voxels()[1]
    assert occ.min() >= 0.3 - 1e-6 and occ.max() <= 0.8 + 1e-6
    assert plain.voxels()[1].max() > 0.9
    # The projective model is its own map of the same scene.
    centres = mrfmap.build_dataset(dataset, resolution=0.2, marking="centres")
    assert len(centres) > 0 and (centres.voxels()[1] > 0.5).any()
    # A map over the memory limit is refused before any work, as `mrfmap build` refuses it
    # (about 3 GiB at 0.01 m here).
    monkeypatch.setenv("MRFMAP_MAX_MEMORY", "32M")
    with pytest.raises(MemoryError, match="memory"):
        mrfmap.build_dataset(dataset, resolution=0.01)
    monkeypatch.delenv("MRFMAP_MAX_MEMORY")
    for bad, message in [
        (dict(marking="ray"), "unknown marking"),
        (dict(clamp=(0.9, 0.2)), "0 < MIN < MAX < 1"),
        (dict(iterations=0), "at least 1"),
        (dict(engine="mrf", keyframes="some"), "unknown keyframe selection"),
    ]:
        with pytest.raises(ValueError, match=message):
            mrfmap.build_dataset(dataset, resolution=0.2, **bad)


def dask_or_skip():
    if os.environ.get("MRFMAP_REQUIRE_DASK"):
        import distributed  # noqa: F401  (build-and-test.sh installs it: missing is a failure)
    else:
        pytest.importorskip("distributed", reason="needs dask[distributed] (pip install 'mrfmap[distributed]')")


def test_distributed_tiles_equal_the_whole_map(tmp_path):
    dask_or_skip()
    from distributed import Client, LocalCluster

    import mrfmap.distributed as md

    dataset = small_floor(tmp_path)
    whole = mrfmap.build_dataset(dataset, resolution=0.1)
    out = tmp_path / "tiles"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        with Client(cluster) as client:
            summary = md.build(dataset, out, tile=3.2, resolution=0.1, client=client, progress=False)
    assert summary["tiles"] >= 9 and 30 <= summary["frames"] <= 40
    tiled = mrfmap.load_map(out)
    assert len(tiled) == len(whole) == summary["voxels"]
    order = lambda c: np.lexsort(c.T)  # noqa: E731
    (cw, ow, _), (ct, ot, _) = whole.voxels(), tiled.voxels()
    iw, it = order(cw), order(ct)
    assert np.array_equal(cw[iw], ct[it])
    assert np.array_equal(ow[iw], ot[it]), "log-odds tiles must equal the whole map exactly"
    # Bad options are refused before any work.
    with pytest.raises(ValueError, match="whole number of bricks"):
        md.build(dataset, tmp_path / "bad", tile=1.0, resolution=0.3)
    with pytest.raises(ValueError, match="unknown option"):
        mrfmap.build_dataset(dataset, resolution=0.1, colour="red")
