#!/usr/bin/env python3
"""Writes a large synthetic depth-camera bag for the streaming benchmark (issue #37).

usage: bench/big_bag.py OUT [--images 6000] [--format mcap|db3|ros1] [--width 640] [--height 480]

A camera (fx = fy = 525, 640 x 480, 16UC1 millimetres on /camera/depth/image_rect_raw, its
CameraInfo beside it) walks a slow loop inside a 10 m x 8 m x 3 m box room at 30 Hz; each image
is the room's depth seen from its pose, computed exactly (ray against the box's six planes).
Poses go on /tf (map -> camera_depth_optical) at every image's stamp. 6,000 images are about
3.7 GB. Build with `--depth-topic /camera/depth/image_rect_raw --fixed-frame map`.
Needs `rosbags` and `numpy` (the rosbags venv of .ci/run has both).
"""
import argparse
import math
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

ap = argparse.ArgumentParser()
ap.add_argument("out")
ap.add_argument("--images", type=int, default=6000)
ap.add_argument("--format", choices=["mcap", "db3", "ros1"], default="mcap")
ap.add_argument("--width", type=int, default=640)
ap.add_argument("--height", type=int, default=480)
a = ap.parse_args()
ros1 = a.format == "ros1"
ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
if "tf2_msgs/msg/TFMessage" not in ts.types:
    from rosbags.typesys import get_types_from_msg

    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
T = ts.types
Image, Info, Time, ROI = T["sensor_msgs/msg/Image"], T["sensor_msgs/msg/CameraInfo"], T["builtin_interfaces/msg/Time"], T["sensor_msgs/msg/RegionOfInterest"]
TF, TS, Tr, V3, Q = (T[n] for n in ["tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped", "geometry_msgs/msg/Transform", "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion"])
Header = (lambda **kw: T["std_msgs/msg/Header"](seq=0, **kw)) if ros1 else T["std_msgs/msg/Header"]
ser = lambda m: (ts.serialize_ros1 if ros1 else ts.serialize_cdr)(m, m.__msgtype__)

w_, h_, f = a.width, a.height, 525.0
cx, cy = (w_ - 1) / 2, (h_ - 1) / 2
u, v = np.meshgrid(np.arange(w_), np.arange(h_))
rays = np.stack([(u - cx) / f, (v - cy) / f, np.ones_like(u, dtype=float)], axis=-1)  # z = 1
room_lo, room_hi = np.array([0.0, 0.0, 0.0]), np.array([10.0, 8.0, 3.0])


def pose(k):
    """Camera k: on a loop around the room's middle at 1.4 m, looking outwards and ahead."""
    a_ = 2 * math.pi * k / 900.0  # one loop per 30 s
    p = np.array([5.0 + 2.5 * math.cos(a_), 4.0 + 2.0 * math.sin(a_), 1.4])
    yaw = a_ + 0.6
    fwd = np.array([math.cos(yaw), math.sin(yaw), -0.1])
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    r = np.stack([right, down, fwd], axis=1)  # columns: camera x, y, z in the world
    return p, r


def quaternion(r):
    """[x, y, z, w] of a rotation matrix."""
    t = np.trace(r)
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k]) * 2
    q = [0.0, 0.0, 0.0, 0.0]
    q[i], q[j], q[k], q[3] = 0.25 * s, (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s, (r[k, j] - r[j, k]) / s
    return q


def depth_mm(p, r):
    """z-depth in millimetres of the box room's walls from camera pose (p, r)."""
    d = rays @ r.T  # world direction per pixel, camera z = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = np.where(d > 0, (room_hi - p) / d, np.inf)
        t_lo = np.where(d < 0, (room_lo - p) / d, np.inf)
    z = np.minimum(t_hi, t_lo).min(axis=-1)  # the ray's parameter is z-depth (camera z = 1)
    return np.clip(np.round(z * 1000), 0, 65535).astype("<u2")


out = Path(a.out)
plugin = StoragePlugin.SQLITE3 if a.format == "db3" else StoragePlugin.MCAP
optical = "camera_depth_optical"
with (Writer1(out) if ros1 else Writer(out, version=8, storage_plugin=plugin)) as w:
    c_img = w.add_connection("/camera/depth/image_rect_raw", Image.__msgtype__, typestore=ts)
    c_info = w.add_connection("/camera/depth/camera_info", Info.__msgtype__, typestore=ts)
    c_tf = w.add_connection("/tf", TF.__msgtype__, typestore=ts)
    k_ = np.array([f, 0, cx, 0, f, cy, 0, 0, 1], dtype=np.float64)
    for k in range(a.images):
        t = 100.0 + k / 30.0
        stamp = Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        ns = int(round(t * 1e9))
        hdr = Header(stamp=stamp, frame_id=optical)
        p, r = pose(k)
        q = quaternion(r)
        tr = Tr(translation=V3(x=p[0], y=p[1], z=p[2]), rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3]))
        w.write(c_tf, ns, ser(TF(transforms=[TS(header=Header(stamp=stamp, frame_id="map"), child_frame_id=optical, transform=tr)])))
        if k % 30 == 0:
            mats = dict(D=np.zeros(5), K=k_, R=np.eye(3).flatten(), P=np.zeros(12)) if ros1 else dict(d=np.zeros(5), k=k_, r=np.eye(3).flatten(), p=np.zeros(12))
            roi = ROI(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            w.write(c_info, ns, ser(Info(header=hdr, height=h_, width=w_, distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **mats)))
        data = depth_mm(p, r).view(np.uint8).reshape(-1)
        w.write(c_img, ns, ser(Image(header=hdr, height=h_, width=w_, encoding="16UC1", is_bigendian=0, step=w_ * 2, data=data)))
        if k % 500 == 0:
            print(f"{k} of {a.images} images", flush=True)
print(f"wrote {out}")
